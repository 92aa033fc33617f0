"""Frame-source base class: selection, resampling, depth conventions, stamping.

A concrete source reads its native data and returns :class:`common.frame.Frame` objects
at native resolution (``_load``) or streams them (``_iter_native``); this class applies,
in order: frame selection (``index % (frame_skip + 1) == 0``, then ``max_frames``),
resampling to ``resolution`` (RGB area/bilinear, depth/labels/confidence nearest,
intrinsics rescaled), the depth conventions (``sanitize_depth``: ≤0/−inf → NaN, finite >
``depth_limit`` → +inf), and stamps ``robot`` and ``seq`` (0, 1, ... in output order).

A frame that fails to read or decode (a corrupt image or recording frame, a bag message
that does not deserialise, a non-rigid pose) is skipped, not fatal: the source logs one
line naming the frame and the error, counts it in ``skipped["corrupt frame"]`` (one bounded
reason, never the error text) and goes on with the next frame; ``seq`` stays contiguous.
A source that cannot be opened at all still raises :class:`SourceError`.
"""
from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from common.conventions import is_rigid, sanitize_depth
from common.frame import Frame
from common.geometry import scale_intrinsics
from edge.sources.config import SourceConfig
from edge.sources.errors import SourceError
from edge.sources.imageops import parse_resolution, resize_nearest, resize_rgb

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

log = logging.getLogger(__name__)

#: the ``skipped`` reason of frames that failed to read or decode
CORRUPT = "corrupt frame"


class RateLimitedLog:
    """At most one line per key per ``every`` seconds; the next line says how many were held back."""

    def __init__(self, every: float, logger: logging.Logger = log):
        self.every = float(every)
        self.log = logger
        self._last: dict[str, float] = {}
        self._held: Counter = Counter()

    def warn(self, key: str, msg: str, *args: Any) -> None:
        """Log ``msg % args`` as a warning unless ``key`` was logged less than ``every`` seconds ago."""
        now = time.monotonic()
        last = self._last.get(key)
        if last is not None and now - last < self.every:
            self._held[key] += 1
            return
        held = self._held.pop(key, 0)
        self._last[key] = now
        self.log.warning(msg + (f" (+{held} more since the last report)" if held else ""), *args)


def select_indices(candidates: Sequence[int], frame_skip: int, max_frames: int | None) -> list[int]:
    """Source indices kept by ``frame_skip`` (on the source index) and ``max_frames``."""
    if frame_skip < 0:
        raise SourceError(f"frame_skip must be >= 0, got {frame_skip}")
    if max_frames is not None and max_frames < 0:
        raise SourceError(f"max_frames must be >= 0 or null, got {max_frames}")
    keep = [int(i) for i in candidates if int(i) % (frame_skip + 1) == 0]
    return keep if max_frames is None else keep[:max_frames]


class FrameSource:
    """An iterable of posed RGB-D :class:`Frame` objects obeying docs/conventions.md.

    Attributes:
        name: short description (kind and scene).
        world_frame: one sentence saying which world frame the poses are in.
        class_names: label names (index = label id, 0 = none) or ``None``.
        skipped: ``Counter`` of frames dropped by the source, by reason.
    """

    kind = "base"
    default_fps = 10.0

    def __init__(self, cfg: SourceConfig):
        self.cfg = cfg
        self.out_hw = parse_resolution(cfg.resolution)
        if cfg.depth_limit is not None and not cfg.depth_limit >= 0:
            raise SourceError(f"depth_limit must be >= 0 or null, got {cfg.depth_limit}")
        self.name = self.kind
        self.world_frame = ""
        self.class_names: list[str] | None = None
        self.skipped: Counter = Counter()
        self._indices: list[int] = []
        self.native_hw: tuple[int, int] | None = None  # depth resolution as stored
        self.native_K: np.ndarray | None = None  # intrinsics at native_hw

    def _input_path(self, what: str, directory: bool = False) -> Path:
        """``source.path`` as a Path; one-line :class:`SourceError` ("<kind>: <what> not
        found: <path>") when it does not exist (or, with ``directory``, is not a directory)."""
        path = Path(self.cfg.path)
        if not (path.is_dir() if directory else path.exists()):
            raise SourceError(f"{self.kind}: {what} not found: {path}")
        return path

    def _scene_dir(self, root: Path) -> Path:
        """``root / source.scene`` (``root`` itself when scene is empty); one-line
        :class:`SourceError` ("<kind>: scene directory not found: <path>") when it is not a directory."""
        scene = root / self.cfg.scene if self.cfg.scene else root
        if not scene.is_dir():
            raise SourceError(f"{self.kind}: scene directory not found: {scene}")
        return scene

    # ---- to be provided by subclasses -------------------------------------------------
    def _load(self, index: int) -> Frame:
        """The native frame at source ``index`` (robot/seq are filled in later)."""
        raise NotImplementedError

    def _iter_native(self, indices: list[int]) -> Iterator[Frame]:
        """Native frames for ``indices`` in order; default: ``_load`` each, skipping (and
        counting) those that fail to read."""
        for i in indices:
            try:
                f = self._load(i)
            except SourceError as e:
                self._skip_corrupt(i, e)
                continue
            yield f

    # ---- shared ------------------------------------------------------------------------
    @property
    def fps(self) -> float:
        """Nominal frame rate, Hz: ``cfg.fps`` when set, else the source's default."""
        return float(self.cfg.fps) if self.cfg.fps else self.default_fps

    def _select(self, candidates: Sequence[int]) -> None:
        self._indices = select_indices(candidates, self.cfg.frame_skip, self.cfg.max_frames)

    def _skip(self, reason: str, count: int = 1) -> None:
        self.skipped[reason] += count

    def _skip_corrupt(self, index, err: Exception) -> None:
        """Count a frame that could not be read/decoded and log one line about it."""
        self.skipped[CORRUPT] += 1
        log.error("%s: skipping frame %s (%d skipped so far): %s", self.name, index, self.skipped[CORRUPT],
                  str(err)[:300])

    def _report_skips(self) -> None:
        for reason, n in self.skipped.items():
            log.warning("%s: skipped %d frame(s): %s", self.name, n, reason)

    @property
    def indices(self) -> list[int]:
        """Source indices this source will yield, in order."""
        return list(self._indices)

    @property
    def resolution(self) -> tuple[int, int] | None:
        """(H, W) of the yielded depth (``None`` if not known before reading)."""
        return self.out_hw or self.native_hw

    @property
    def intrinsics(self) -> np.ndarray | None:
        """3×3 K at the yielded depth resolution."""
        if self.native_K is None or self.native_hw is None:
            return None
        return scale_intrinsics(self.native_K, self.native_hw, self.out_hw or self.native_hw)

    def __len__(self) -> int:
        return len(self._indices)

    def __iter__(self) -> Iterator[Frame]:
        it = self._iter_native(list(self._indices))
        if self.cfg.progress:
            from tqdm import tqdm

            it = tqdm(it, total=len(self), desc=self.name, unit="frame")
        seq = 0
        for frame in it:
            try:
                out = self._finish(frame, seq)
            except SourceError as e:
                self._skip_corrupt((frame.meta or {}).get("index", "?"), e)
                continue
            seq += 1
            yield out

    def _finish(self, f: Frame, seq: int) -> Frame:
        depth = np.asarray(f.depth)
        if depth.ndim != 2:
            raise SourceError(f"{self.name}: depth must be (H, W), got {depth.shape}")
        K = np.asarray(f.intrinsics, dtype=np.float64)
        hw = depth.shape
        labels, conf, rgb = f.labels, f.confidence, np.asarray(f.rgb)
        if labels is not None and labels.shape[:2] != hw:
            labels = resize_nearest(labels, hw)
        if conf is not None and conf.shape[:2] != hw:
            conf = resize_nearest(conf, hw)
        if self.out_hw is not None and self.out_hw != hw:
            K = scale_intrinsics(K, hw, self.out_hw)
            depth = resize_nearest(depth, self.out_hw)
            labels = None if labels is None else resize_nearest(labels, self.out_hw)
            conf = None if conf is None else resize_nearest(conf, self.out_hw)
        if self.out_hw is not None:
            rgb = resize_rgb(rgb, self.out_hw)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise SourceError(f"{self.name}: rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
        pose = np.asarray(f.pose, dtype=np.float64)
        if not is_rigid(pose):
            raise SourceError(f"{self.name}: frame {f.meta.get('index')} has a non-rigid pose:\n{pose}")
        meta = dict(f.meta)
        meta.setdefault("source", self.kind)
        return Frame(
            robot=self.cfg.robot,
            seq=seq,
            stamp=float(f.stamp),
            pose=pose,
            intrinsics=K,
            depth=sanitize_depth(depth, self.cfg.depth_limit),
            rgb=np.ascontiguousarray(rgb),
            features=f.features,
            feature_space=f.feature_space,
            labels=None if labels is None else np.ascontiguousarray(labels, dtype=np.int32),
            confidence=None if conf is None else np.ascontiguousarray(conf, dtype=np.float32),
            global_feature=f.global_feature,
            meta=meta,
        )

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r}: {len(self)} frames, {self.world_frame}>"


def native_frame(index: int, stamp: float, pose: ArrayLike, K: ArrayLike | None, depth: np.ndarray, rgb: np.ndarray,
                 labels: np.ndarray | None = None, **meta: Any) -> Frame:
    """A native-resolution frame as ``_load`` returns it (robot/seq filled in by the base; ``stamp`` in
    seconds, ``pose`` camera-to-world RDF, ``K`` at the depth resolution; a source sets its
    ``native_K`` before it loads frames, so K None is a bug: ValueError)."""
    if K is None:
        raise ValueError(f"frame {index}: the source has no intrinsics (native_K) yet")
    return Frame(robot="", seq=0, stamp=float(stamp), pose=np.asarray(pose, dtype=np.float64),
                 intrinsics=np.asarray(K, dtype=np.float64), depth=depth, rgb=rgb, labels=labels,
                 meta={"index": int(index), **meta})


def number_rows(path: Path, count: int, layout: str) -> Iterator[list[float]]:
    """The values of each non-blank line of text file ``path``, a line holding exactly ``count``
    whitespace-separated numbers; one-line :class:`SourceError` naming ``path:line``
    otherwise (``layout`` says what the numbers are, e.g. "(a row-major 4×4)")."""
    for ln, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            vals = [float(v) for v in line.split()]
        except ValueError:
            raise SourceError(f"{path}:{ln}: not a list of numbers") from None
        if len(vals) != count:
            raise SourceError(f"{path}:{ln}: expected {count} numbers {layout}, got {len(vals)}")
        yield vals


class DirectorySource(FrameSource):
    """A source read from the dataset directory ``source.path`` (``root``); one-line
    :class:`SourceError` when it is not a directory."""

    def __init__(self, cfg: SourceConfig):
        super().__init__(cfg)
        self.root = self._input_path("directory", directory=True)


def filter_poses(poses: Sequence[np.ndarray] | np.ndarray, what: str, source: FrameSource) -> list[int]:
    """Indices of finite rigid poses; the others are counted in ``source.skipped``."""
    ok = []
    for i, p in enumerate(poses):
        if is_rigid(p):
            ok.append(i)
        else:
            source._skip(f"non-finite or non-rigid pose in {what}")
    return ok
