"""Two-stage map integration: frame N+1 is prepared on a worker thread while frame N is
committed on the caller's thread.

:meth:`RayFrontsMap.integrate` is ``commit(prepare(frame))``. ``prepare`` (validation,
per-frame geometry, feature / RGB sampling: about half of a frame's CPU) reads only the
map's configuration and its random generator; ``commit`` (buffering, the voxel block:
occupancy, fusion, pruning, frontiers; the ray block: prune, association, merge) owns all
map state. :class:`MapPipeline` runs ``prepare`` on one worker thread, in submission order,
and ``commit`` on the thread that calls :meth:`MapPipeline.submit`, so two cores work at
once: torch operations and the C++ kernels (``mapper._rfkernels``, the OpenVDB extension)
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
* Anything that reads or replaces the generator or the pending buffers (snapshots,
  restores) must run after :meth:`drain` (or inside ``with pipeline.paused():``), because a
  frame in flight has already drawn its random numbers.
* The worker thread sets its own torch intra-op thread count (``prepare_threads``, default 1:
  on a 2-core machine one core per stage).
"""
from __future__ import annotations

import threading
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import torch


@dataclass
class Committed:
    """A frame that left the pipeline: ``timings`` (per-stage ms) or the ``error`` it raised."""
    tag: Any
    timings: dict | None
    error: BaseException | None = None


def _init_worker(n: int) -> None:
    torch.set_num_threads(max(1, int(n)))


class MapPipeline:
    """Prepare-ahead integration into one :class:`~mapper.map.RayFrontsMap` (module docstring).

    ``lock`` (optional) is held around every commit, for callers that query the map from
    other threads; prepares never need it."""

    def __init__(self, m, depth: int = 1, prepare_threads: int = 1, lock: threading.Lock | None = None):
        if depth < 1:
            raise ValueError(f"pipeline depth must be >= 1, got {depth}")
        self.map = m
        self.depth = int(depth)
        self.lock = lock
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="map-prepare", initializer=_init_worker,
                                        initargs=(prepare_threads,))
        self._inflight: deque[tuple[Any, Future]] = deque()
        self._closed = False

    def __len__(self) -> int:
        """Frames submitted and not yet committed."""
        return len(self._inflight)

    def submit(self, pose, intrinsics, depth, rgb=None, features=None, global_feature=None, confidence=None,
               *, tag: Any = None) -> list[Committed]:
        """Queue one frame (arguments as :meth:`RayFrontsMap.integrate`); commit the oldest
        frames beyond ``depth`` in flight and return them."""
        if self._closed:
            raise RuntimeError("pipeline is closed")
        fut = self._pool.submit(self.map.prepare, pose, intrinsics, depth, rgb, features, global_feature, confidence)
        self._inflight.append((tag, fut))
        out = []
        while len(self._inflight) > self.depth:
            out.append(self._commit_oldest())
        return out

    def _commit_oldest(self) -> Committed:
        tag, fut = self._inflight.popleft()
        try:
            prepared = fut.result()
        except Exception as e:  # bad input: reported, nothing added
            return Committed(tag, None, e)
        if self.lock is not None:
            with self.lock:
                return Committed(tag, self.map.commit(prepared))
        return Committed(tag, self.map.commit(prepared))

    def drain(self) -> list[Committed]:
        """Commit every frame in flight (in order) and return them."""
        out = []
        while self._inflight:
            out.append(self._commit_oldest())
        return out

    @contextmanager
    def paused(self):
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
        return out

    def __enter__(self) -> "MapPipeline":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["MapPipeline", "Committed"]
