"""A recording directory (``common.recording``: what an edge sent, or what ``rayfronts
world`` rendered) replayed as a frame source.

Frames come back as recorded (pose, stamp, intrinsics, labels, features if any); this
source re-applies frame selection, ``resolution`` and ``depth_limit`` and re-stamps
``robot`` (the configured robot id) and ``seq``. ``class_names`` come from the
recording's ``recording.yaml`` (``class_names`` / ``classes``, at the top level or in its
``source`` dict). Intrinsics are read from the first selected frame.

A corrupt frame file (one that does not decode) is skipped and counted
(``skipped["corrupt frame"]``, one log line), and the frames after it are still read.

World frame: whatever frame the recorder wrote (the recorded frames already obey the
conventions: RDF camera-to-world; z-up for the synthetic world and the converted sources).
"""
from __future__ import annotations

import numpy as np

from edge.sources.base import DirectorySource
from edge.sources.config import SourceConfig
from edge.sources.errors import SourceError


def _find(info: dict, *keys):
    for d in (info, s if isinstance(s := info.get("source"), dict) else {}):
        for k in keys:
            if d.get(k):
                return d[k]
    return None


class RecordingSource(DirectorySource):
    kind = "recording"

    def __init__(self, cfg: SourceConfig):
        super().__init__(cfg)
        try:
            from common.recording import RecordingError, RecordingReader
        except ImportError as e:
            raise SourceError(f"recording: the recording reader (common.recording) is not available: {e}") from None
        self._RecordingError = RecordingError
        try:
            self.reader = RecordingReader(self.root)
        except (RecordingError, OSError, ValueError) as e:
            raise SourceError(f"recording: cannot open {self.root}: {e}") from None
        self.info = dict(self.reader.info or {})
        names = _find(self.info, "class_names", "classes")
        self.class_names = [str(n) for n in names] if names else None
        src = s if isinstance(s := self.info.get("source"), dict) else {}
        self.name = f"recording:{self.root.name}"
        if src.get("type") == "synthetic_world":
            self.world_frame = "synthetic world frame, z up (x east, y north), ground at z = 0 (recorded)"
        else:
            self.world_frame = "the recorded world frame (RDF camera-to-world poses as the recorder wrote them)"
        self.default_fps = 1.0 / float(src["frame_dt"]) if src.get("frame_dt") else 10.0
        self._select(range(len(self.reader)))
        for i in self._indices:   # intrinsics from the first selected frame that decodes
            try:
                f = self._read(i)
            except SourceError:
                continue          # counted when the iteration reaches it
            self.native_K, self.native_hw = np.asarray(f.intrinsics, dtype=np.float64), tuple(f.depth.shape)
            break

    def _read(self, i: int):
        try:
            f = self.reader[i]
        except self._RecordingError as e:
            raise SourceError(f"recording: {e}") from None
        f.meta = {**(f.meta or {}), "index": i}
        return f

    def _load(self, i: int):
        return self._read(i)
