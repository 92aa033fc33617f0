"""Two-stage map integration: frame N+1 is prepared on a worker thread while frame N is
committed on the caller's thread.

:meth:`RayFrontsMap.integrate` is ``commit(prepare(frame))``. ``prepare`` (validation,
per-frame geometry, feature / RGB sampling: about half of a frame's CPU) reads only the
map's configuration and its random generator; ``commit`` (buffering, the voxel block:
occupancy, fusion, pruning, frontiers; the ray block: prune, association, merge) owns all
map state. :class:`MapPipeline` runs ``prepare`` on one worker thread, in submission order,
and ``commit`` on the thread that calls :meth:`MapPipeline.submit`, so two cores work at
once: torch operations and the C++ kernels (``semantic_map._rfkernels``, the OpenVDB extension)
release the GIL while they compute.

Maps are identical to the sequential path: prepares run one at a time in frame order, so
the generator's draws are the same, and commits run in the same order
(``tests/test_mapper_pipeline.py`` compares every array of both maps).

Decisions:

* ``depth`` (default 1) frames may be prepared ahead; :meth:`submit` returns the frames it
  committed (usually the previous one). A frame is only committed when a later frame is
  submitted or on :meth:`drain` — a live service calls :meth:`drain` whenever its input
  queue is empty, so a slow robot's frames are not held back.
* A frame whose prepare raises (bad input) is reported in its :class:`Committed` entry
  (``error``) at the point it would have been committed; nothing is added to the map and
  later frames are unaffected.
* Snapshots stay exact while frames are in flight: the worker records the generator's
  state before each prepare (under a lock it holds while preparing), and the map's
  :meth:`~semantic_map.map.RayFrontsMap.rng_state` (what :mod:`mapper.snapshot` saves) answers the
  state before the oldest uncommitted frame — the state the sequential path would have
  after the last committed frame. Replacing the map's generator (a restore) must run after
  :meth:`drain`.
* ``commit`` (default ``map.commit``) is what the caller's thread runs per prepared frame;
  the mapper service passes its own (lock, versions); an exception there is reported in
  that frame's :class:`Committed` entry like a prepare error.
* The worker thread sets its own torch intra-op thread count (``prepare_threads``, default 1:
  on a 2-core machine one core per stage).
"""
from __future__ import annotations

import threading
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Iterator

import torch

if TYPE_CHECKING:
    from semantic_map.depth_geometry import ArrayOrTensor
    from semantic_map.map import PreparedFrame, RayFrontsMap


@dataclass
class Committed:
    """A frame that left the pipeline: ``timings`` (per-stage ms) or the ``error`` it raised."""
    tag: Any
    timings: dict | None
    error: BaseException | None = None
    cpu_ms: float = 0.0   # thread CPU of this frame's prepare + commit


def _init_worker(n: int) -> None:
    torch.set_num_threads(max(1, int(n)))


class MapPipeline:
    """Prepare-ahead integration into one :class:`~semantic_map.map.RayFrontsMap` (module docstring).

    ``lock`` (optional) is held around every commit, for callers that query the map from
    other threads; prepares never need it."""

    def __init__(self, m: RayFrontsMap, depth: int = 1, prepare_threads: int = 1, lock: threading.Lock | None = None,
                 commit: Callable[[PreparedFrame], dict[str, float]] | None = None) -> None:
        if depth < 1:
            raise ValueError(f"pipeline depth must be >= 1, got {depth}")
        self.map = m
        self.depth = int(depth)
        self.lock = lock
        self._commit = commit
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="map-prepare", initializer=_init_worker,
                                        initargs=(prepare_threads,))
        self._inflight: deque[tuple[Any, Future, int]] = deque()
        self._seq = 0
        self._gen_lock = threading.Lock()
        self._before: dict[int, torch.Tensor] = {}
        self._closed = False
        m.attach_rng_state_source(self.committed_rng_state)

    def __len__(self) -> int:
        """Frames submitted and not yet committed."""
        return len(self._inflight)

    def committed_rng_state(self) -> torch.Tensor:
        """The generator state after the last committed frame (see module docstring)."""
        with self._gen_lock:
            for _, _, seq in self._inflight:  # oldest first
                if seq in self._before:
                    return self._before[seq].clone()
                break
            return self.map.prepared_rng_state()

    def _prepare(self, seq: int, args: tuple) -> tuple[PreparedFrame, float]:
        import time
        c0 = time.thread_time()
        with self._gen_lock:
            self._before[seq] = self.map.prepared_rng_state()
            p = self.map.prepare(*args)
        return p, (time.thread_time() - c0) * 1e3

    def submit(self, pose: ArrayOrTensor, intrinsics: ArrayOrTensor, depth: ArrayOrTensor,
               rgb: ArrayOrTensor | None = None, features: ArrayOrTensor | None = None,
               global_feature: ArrayOrTensor | None = None, confidence: ArrayOrTensor | None = None,
               *, tag: Any = None) -> list[Committed]:
        """Queue one frame (arguments as :meth:`RayFrontsMap.integrate`); commit the oldest
        frames beyond ``depth`` in flight and return them."""
        if self._closed:
            raise RuntimeError("pipeline is closed")
        seq = self._seq
        self._seq += 1
        with self._gen_lock:  # committed_rng_state() reads the queue from other threads
            fut = self._pool.submit(self._prepare, seq,
                                    (pose, intrinsics, depth, rgb, features, global_feature, confidence))
            self._inflight.append((tag, fut, seq))
        out = []
        while len(self._inflight) > self.depth:
            out.append(self._commit_oldest())
        return out

    def _commit_oldest(self) -> Committed:
        import time
        tag, fut, seq = self._inflight[0]
        try:
            prepared, cpu = fut.result()
        except Exception as e:  # bad input: reported, nothing added
            self._pop(seq)
            return Committed(tag, None, e)
        c0 = time.thread_time()
        try:
            if self._commit is not None:
                tm = self._commit(prepared)
            elif self.lock is not None:
                with self.lock:
                    tm = self.map.commit(prepared)
            else:
                tm = self.map.commit(prepared)
        except Exception as e:
            self._pop(seq)
            return Committed(tag, None, e, cpu + (time.thread_time() - c0) * 1e3)
        self._pop(seq)
        return Committed(tag, tm, None, cpu + (time.thread_time() - c0) * 1e3)

    def _pop(self, seq: int) -> None:
        with self._gen_lock:
            self._inflight.popleft()
            self._before.pop(seq, None)

    def drain(self) -> list[Committed]:
        """Commit every frame in flight (in order) and return them."""
        out = []
        while self._inflight:
            out.append(self._commit_oldest())
        return out

    @contextmanager
    def paused(self) -> Iterator[MapPipeline]:
        """Drain, then run the body with nothing in flight (snapshots, restores)."""
        self.drain()
        yield self

    def close(self) -> list[Committed]:
        """Drain and stop the worker thread."""
        if self._closed:
            return []
        out = self.drain()
        self._closed = True
        self._pool.shutdown(wait=True)
        self.map.detach_rng_state_source(self.committed_rng_state)
        return out

    def __enter__(self) -> "MapPipeline":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["MapPipeline", "Committed"]
