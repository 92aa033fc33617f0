"""Why the fleet runtime comparison (``tests/test_fleet_runtime.py::test_three_bases_...``)
needs every edge lossless: its one flaky failure (``'car': max_abs 0.31, mean_abs 0.0005``)
was a frame missing from one of the two compared runs, not the robots' interleaving.

Measured in process (the test's 3 x 10 frames at 48x64, throughput preset, vox 0.5 m; the
edge chain: label encoder, PCA-16, wire round trip): four random interleavings of the three
robots, with idle flushes at random points, change no voxel score by more than 4e-4 (the
float16 rounding of the running mean); leaving out any one of the 30 frames changes a car
score by 0.09-0.35 (mean_abs 1.3e-4-5.7e-4), r1's frame 7 by exactly 0.31 / 0.0005. Before
``publish.lossless`` the test accepted a run with up to two frames fewer per robot.

Here: the edge's hand-off to its publisher under a publisher that cannot keep up (a loaded
host): lossless, every frame is sent, in order; otherwise unsent frames are replaced (what a
live camera wants, what broke the comparison)."""
from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np
import pytest
import torch

from common.frame import Frame
from edge.config import EdgeConfig, PublishSection
from edge.runtime import EdgeRuntime, _RunState

N = 8


def _frames() -> list[Frame]:
    K = np.array([[4.0, 0, 4], [0, 4.0, 4], [0, 0, 1]])
    return [Frame(robot="r0", seq=i, stamp=0.1 * i, pose=np.eye(4), intrinsics=K,
                  depth=np.full((8, 8), 2.0, np.float32), rgb=np.zeros((8, 8, 3), np.uint8))
            for i in range(N)]


def _runtime(lossless: bool) -> tuple[EdgeRuntime, _RunState]:
    pub = dataclasses.replace(PublishSection(), rate_hz=0, lossless=lossless, feature_codec="f16")
    rt = EdgeRuntime(EdgeConfig(robot="r0", publish=pub))
    st = _RunState(rate=0.0, next_t=time.monotonic())
    rt.chain.fs = type("Space", (), {"id": "label-minilm-l6.1-000000000000-4"})()
    return rt, st


def _send_all(rt: EdgeRuntime, st: _RunState) -> None:
    """What ``EdgeRuntime._run`` does per encoded frame: hand it over (one frame at a time)."""
    feats = torch.zeros((4, 2, 2))
    for fr in _frames():
        rt._send_frames(st, [(fr, feats, None)], time.perf_counter())


@pytest.mark.timeout(60)
def test_lossless_edge_sends_every_frame_to_a_slow_publisher():
    rt, st = _runtime(lossless=True)
    got: list[int] = []

    def slow_publisher():              # 20 ms per put, far slower than the encoder
        while len(got) < N:
            time.sleep(0.02)
            item = rt.slot.get(timeout=10.0)
            if item is None:
                return
            got.append(item[0].seq)

    t = threading.Thread(target=slow_publisher)
    t.start()
    _send_all(rt, st)
    t.join(20)
    assert got == list(range(N)) and rt.slot.replaced == 0, (got, rt.slot.replaced)


def test_live_edge_replaces_unsent_frames():
    """The default (a live camera): a publisher stalled while frames come loses all but the newest."""
    rt, st = _runtime(lossless=False)
    _send_all(rt, st)                  # the publisher takes nothing meanwhile
    item = rt.slot.get(timeout=1.0)
    assert item is not None and item[0].seq == N - 1 and rt.slot.replaced == N - 1
