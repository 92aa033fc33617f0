"""Recording directory format: wire-encoded frames on disk (what an edge sent, or what
``rayfronts world`` rendered), replayable by any frame source.

Layout::

    DIR/recording.yaml          format: rayfronts.recording, version: 1, robot, created (ISO 8601 UTC),
                                updated, frames (count), feature_space, encoding, source (free-form dict)
    DIR/frames/000000.rff       exact bytes of common.wire.encode_frame, index order
    DIR/frames/000001.rff ...

Crash safety: ``recording.yaml`` is written when the writer opens, rewritten atomically
(temp file + rename) every ``flush_every`` frames and on close; frame files are written
atomically too. A reader therefore always sees a valid yaml and whole frame files; if the
writer died, frame files beyond the yaml's count are still read (the files on disk are
the truth, the count in the yaml is a lower bound).
"""
from __future__ import annotations

import datetime
import os
import re
import tempfile
from pathlib import Path
from typing import Any, Iterator

import yaml

from common.frame import Frame
from common.wire import WireError, WireLimits, decode_frame, encode_frame, validate_robot_id

__all__ = [
    "RecordingError",
    "RecordingWriter",
    "RecordingReader",
    "RECORDING_FORMAT",
    "RECORDING_VERSION",
    "FRAME_SUFFIX",
]

RECORDING_FORMAT = "rayfronts.recording"
RECORDING_VERSION = 1
FRAME_SUFFIX = ".rff"
_YAML = "recording.yaml"
_FRAMES = "frames"
_FRAME_RE = re.compile(r"(\d{6,})\.rff")
_ENCODE_KWARGS = ("jpeg_quality", "depth_codec", "rgb_codec")


class RecordingError(Exception):
    """A recording cannot be written or read; the message names the path and the reason."""


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temp file in the same directory and a rename."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o644)  # mkstemp makes 0600 files
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _plain(x: Any) -> Any:
    """Tuples → lists and numpy scalars/arrays → Python values, so safe_dump accepts them."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if hasattr(x, "tolist") and type(x).__module__ == "numpy":
        return x.tolist()
    if isinstance(x, os.PathLike):
        return os.fspath(x)
    return x


def frame_file_name(index: int) -> str:
    """``{index:06d}.rff``."""
    return f"{index:06d}{FRAME_SUFFIX}"


class RecordingWriter:
    """Writes a recording directory; use as a context manager.

    Args:
        path: the recording directory (created, with parents).
        robot: robot id of every frame in it (frames of another robot are refused).
        source: free-form, YAML-serialisable description of where the frames came from
            (tuples, numpy values and paths are converted; a str becomes ``{"kind": str}``).
        overwrite: replace an existing recording in ``path`` (only ``recording.yaml`` and
            ``frames/*.rff`` are removed); otherwise an existing recording is an error.
        flush_every: rewrite ``recording.yaml`` every this many frames (≥ 1).
        **encode_kwargs: passed to :func:`common.wire.encode_frame`
            (``jpeg_quality``, ``depth_codec``, ``rgb_codec``).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        robot: str,
        source: dict | str | None = None,
        overwrite: bool = False,
        flush_every: int = 10,
        **encode_kwargs: Any,
    ) -> None:
        self.path = Path(path)
        unknown = sorted(set(encode_kwargs) - set(_ENCODE_KWARGS))
        if unknown:
            raise TypeError(f"RecordingWriter: unknown encode options {unknown} (known: {list(_ENCODE_KWARGS)})")
        try:
            validate_robot_id(robot)
        except WireError as e:
            raise RecordingError(f"{self.path}: {e}") from None
        if isinstance(source, str):
            source = {"kind": source}
        if source is not None and not isinstance(source, dict):
            raise RecordingError(f"{self.path}: source must be a dict (or a str), got {type(source).__name__}")
        if type(flush_every) is not int or flush_every < 1:
            raise RecordingError(f"{self.path}: flush_every must be an int >= 1, got {flush_every!r}")
        self.robot = robot
        self.encode_kwargs = dict(encode_kwargs)
        self.flush_every = flush_every
        self._count = 0
        self._closed = False
        self._info: dict[str, Any] = {
            "format": RECORDING_FORMAT,
            "version": RECORDING_VERSION,
            "robot": robot,
            "created": _now(),
            "updated": None,
            "frames": 0,
            "feature_space": None,
            "first_stamp": None,
            "last_stamp": None,
            "encoding": dict(self.encode_kwargs),
            "source": _plain(dict(source or {})),
        }
        try:
            yaml.safe_dump(self._info["source"])
        except yaml.YAMLError as e:
            raise RecordingError(f"{self.path}: source is not YAML-serialisable ({e})") from e

        frames = self.path / _FRAMES
        yml = self.path / _YAML
        try:
            if self.path.exists() and not self.path.is_dir():
                raise RecordingError(f"{self.path}: exists and is not a directory")
            existing = yml.exists() or (frames.is_dir() and any(frames.glob(f"*{FRAME_SUFFIX}")))
            if existing and not overwrite:
                raise RecordingError(f"{self.path}: already holds a recording (pass overwrite=True to replace it)")
            frames.mkdir(parents=True, exist_ok=True)
            if existing:
                for f in frames.glob(f"*{FRAME_SUFFIX}"):
                    f.unlink()
            self._write_yaml()
        except OSError as e:
            raise RecordingError(f"{self.path}: cannot create the recording ({e})") from e

    # ---- properties

    @property
    def frames_dir(self) -> Path:
        return self.path / _FRAMES

    def __len__(self) -> int:
        return self._count

    @property
    def info(self) -> dict:
        """The current ``recording.yaml`` content."""
        return dict(self._info)

    # ---- writing

    def write(self, frame: Frame) -> Path:
        """Encode ``frame`` and write it as the next frame file; returns its path."""
        self._check_open()
        if frame.robot != self.robot:
            raise RecordingError(f"{self.path}: frame of robot {frame.robot!r} in a recording of robot {self.robot!r}")
        try:
            data = encode_frame(frame, **self.encode_kwargs)
        except WireError as e:
            raise RecordingError(f"{self.path}: frame {self._count} cannot be encoded: {e}") from e
        return self._append(data, frame.feature_space, frame.stamp)

    def write_encoded(self, data: bytes | bytearray | memoryview, limits: WireLimits | None = None) -> Path:
        """Write an already-encoded frame message as is (e.g. what the mapper received),
        after checking that it decodes."""
        self._check_open()
        try:
            frame = decode_frame(data, limits)
        except WireError as e:
            raise RecordingError(f"{self.path}: frame {self._count} is not a valid frame message: {e}") from e
        if frame.robot != self.robot:
            raise RecordingError(f"{self.path}: frame of robot {frame.robot!r} in a recording of robot {self.robot!r}")
        return self._append(bytes(data), frame.feature_space, frame.stamp)

    def _append(self, data: bytes, feature_space: str, stamp: float) -> Path:
        fs = self._info["feature_space"]
        if fs is None:
            self._info["feature_space"] = feature_space
        elif feature_space != fs:
            raise RecordingError(
                f"{self.path}: frame {self._count} has feature space {feature_space!r}, "
                f"the recording has {fs!r} (a recording never mixes feature spaces)"
            )
        out = self.frames_dir / frame_file_name(self._count)
        try:
            _atomic_write(out, data)
        except OSError as e:
            raise RecordingError(f"{out}: cannot write the frame ({e})") from e
        self._count += 1
        if self._info["first_stamp"] is None:
            self._info["first_stamp"] = float(stamp)
        self._info["last_stamp"] = float(stamp)
        if self._count % self.flush_every == 0:
            self.flush()
        return out

    def flush(self) -> None:
        """Rewrite ``recording.yaml`` now (atomically)."""
        self._check_open()
        self._write_yaml()

    def close(self) -> None:
        """Write the final ``recording.yaml``. Idempotent."""
        if self._closed:
            return
        self._write_yaml()
        self._closed = True

    def _write_yaml(self) -> None:
        self._info["frames"] = self._count
        self._info["updated"] = _now()
        text = yaml.safe_dump(self._info, sort_keys=False)
        try:
            _atomic_write(self.path / _YAML, text.encode())
        except OSError as e:
            raise RecordingError(f"{self.path / _YAML}: cannot write ({e})") from e

    def _check_open(self) -> None:
        if self._closed:
            raise RecordingError(f"{self.path}: the writer is closed")

    def __enter__(self) -> "RecordingWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class RecordingReader:
    """Reads a recording directory: ``len()``, iteration (Frames in index order),
    ``reader[i]`` (negative indices allowed), ``.info`` (the yaml dict).

    Raises :class:`RecordingError` naming the path for a missing directory, a missing or
    invalid ``recording.yaml``, an unsupported version, missing frame files, and a corrupt
    frame file (with the wire error).
    """

    def __init__(self, path: str | os.PathLike, *, limits: WireLimits | None = None) -> None:
        self.path = Path(path)
        self.limits = limits
        if not self.path.is_dir():
            raise RecordingError(f"{self.path}: recording directory does not exist")
        yml = self.path / _YAML
        if not yml.is_file():
            raise RecordingError(f"{yml}: missing (not a recording directory?)")
        try:
            info = yaml.safe_load(yml.read_text())
        except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
            raise RecordingError(f"{yml}: cannot read it as YAML ({e})") from e
        if not isinstance(info, dict):
            raise RecordingError(f"{yml}: expected a mapping, got {type(info).__name__}")
        if info.get("format") != RECORDING_FORMAT:
            raise RecordingError(f"{yml}: format is {info.get('format')!r}, expected {RECORDING_FORMAT!r}")
        if info.get("version") != RECORDING_VERSION:
            raise RecordingError(
                f"{yml}: unsupported version {info.get('version')!r} (this reader reads {RECORDING_VERSION})"
            )
        count = info.get("frames")
        if type(count) is not int or count < 0:
            raise RecordingError(f"{yml}: 'frames' must be an int >= 0, got {count!r}")
        if not isinstance(info.get("robot"), str):
            raise RecordingError(f"{yml}: 'robot' must be a str, got {info.get('robot')!r}")
        self.info: dict[str, Any] = info
        self._files = self._list_frames(count)

    def _list_frames(self, count: int) -> list[Path]:
        d = self.path / _FRAMES
        indices: dict[int, Path] = {}
        if d.is_dir():
            for p in d.iterdir():
                m = _FRAME_RE.fullmatch(p.name)
                if m:
                    indices[int(m.group(1))] = p
        n = 0
        while n in indices:
            n += 1
        if n < count:
            raise RecordingError(
                f"{d / frame_file_name(n)}: missing (recording.yaml says {count} frames)"
            )
        return [indices[i] for i in range(n)]

    def __len__(self) -> int:
        return len(self._files)

    def frame_path(self, i: int) -> Path:
        """Path of frame ``i`` (negative indices allowed)."""
        n = len(self._files)
        if type(i) is not int and not hasattr(i, "__index__"):
            raise TypeError(f"recording indices must be integers, got {type(i).__name__}")
        i = int(i)
        if not -n <= i < n:
            raise IndexError(f"{self.path}: frame index {i} out of range (recording has {n} frames)")
        return self._files[i]

    def read_bytes(self, i: int) -> bytes:
        """The exact encoded bytes of frame ``i``."""
        p = self.frame_path(i)
        try:
            return p.read_bytes()
        except OSError as e:
            raise RecordingError(f"{p}: cannot read ({e})") from e

    def __getitem__(self, i: int) -> Frame:
        p = self.frame_path(i)
        data = self.read_bytes(i)
        try:
            return decode_frame(data, self.limits)
        except WireError as e:
            raise RecordingError(f"{p}: corrupt frame: {e}") from e

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self._files)):
            yield self[i]

    def __repr__(self) -> str:
        return f"RecordingReader({str(self.path)!r}, frames={len(self)}, robot={self.info.get('robot')!r})"
