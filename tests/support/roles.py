"""The rayfronts roles as the process-level tests run them: a mapper (router mode, the base
station) and edges (client mode) on loopback, a small fast map, a PCA basis fitted once per
session, query clients that retry their connection every 0.2 s."""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

from common.zenoh_session import ZenohConfig
from tests.support.processes import ROOT, cli_cmd, proc_env

RES = "96x128"
FAST_MAP = ["preset=throughput", "map.vox_size=0.5", "map.depth_limit=20", "layers.rate_hz=0",
            "rerun.file=", "snapshots.on_exit=false"]


def fit_pca(out: Path) -> Path:
    """A fixed PCA basis (``rayfronts edge fit-pca``) at ``out``, so restarted edges share one
    feature space (the ``pca_file`` fixture fits it once per session)."""
    r = subprocess.run(cli_cmd("edge", "fit-pca", "--out", str(out), "--frames", "4", f"source.resolution={RES}",
                               "source.n_frames=40", "pca.out_dim=16"),
                       env=proc_env(), cwd=str(ROOT), capture_output=True, timeout=120)
    assert r.returncode == 0, r.stderr.decode()[-2000:]
    assert out.is_file()
    return out


def edge_args(ep, pca, robot="r1", frames=40, rate=5.0, extra=()):
    return ["edge", "--connect", ep, "--rate", str(rate), f"robot={robot}", f"source.resolution={RES}",
            f"source.n_frames={frames}", "source.depth_limit=20", f"pca.basis={pca}", "pca.out_dim=16",
            "zenoh.connect_retry_s=0.2", *extra]


def mapper_args(ep, extra=()):
    return ["mapper", "--mode", "router", "--listen", ep, *FAST_MAP, *extra]


def client(ep):
    from query_client import Client

    return Client(ZenohConfig(connect=[ep], connect_timeout_ms=60_000, connect_retry_s=0.2), timeout=20.0)


def mapped(c, robot=None) -> int:
    st = c.stats(timeout=5.0)
    return st["robots"].get(robot, {}).get("mapped", 0) if robot else st["frames"]["mapped"]


def zenoh_client_config(ep: str):
    """A plain ``zenoh.Config`` in client mode connecting to ``ep`` (no multicast scouting)."""
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", '"client"')
    c.insert_json5("connect/endpoints", json.dumps([ep]))
    c.insert_json5("scouting/multicast/enabled", "false")
    return c


class SampleLog:
    """What one Zenoh subscriber on ``key`` receives: ``samples`` holds ``(key, payload bytes,
    attachment bytes or None)`` in arrival order (guarded by ``lock``)."""

    def __init__(self, session, key: str):
        import threading

        self.lock = threading.Lock()
        self.samples: list = []
        self.sub = session.declare_subscriber(key, self._cb)

    def _cb(self, sample) -> None:
        with self.lock:
            self.samples.append((str(sample.key_expr), sample.payload.to_bytes(),
                                 None if sample.attachment is None else sample.attachment.to_bytes()))

    def latest(self):
        """The last sample received, or None."""
        with self.lock:
            return self.samples[-1] if self.samples else None
