"""The closed loop over real processes (``rayfronts eval search --distributed``): a mapper and
the robot's edge run as ``rayfronts mapper`` / ``rayfronts edge`` processes over loopback
Zenoh; this process is the simulator and the planner client.

Per step the simulator puts the step's camera poses on ``<p>/robots/<robot>/sim/views``; the
edge (``source.kind=sim_camera``) renders them, encodes, compresses and publishes the frames;
the mapper fuses them. The planner waits until the mapper has mapped (or dropped) every frame
sent, then asks :meth:`query_client.client.Client.search` (a one-shot search first has the
mapper flush the frames its map buffers) and :meth:`~query_client.client.Client.occupancy_slice`
— what a planner on another machine does.

The edge runs the in-process loop's settings (:class:`apps.closed_loop.sensing.EdgeChain`:
label encoder, its PCA basis from a file, the q16z codec, no-return sky) and the mapper the
same map config, so both modes map the same frames into the same map. Lengths in metres.
"""
from __future__ import annotations

import dataclasses
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from apps.closed_loop.world_model import Observation
from apps.processes import stop_process, wait_for

#: seconds to wait for the processes to start (the first start loads torch and the text model)
START_S = 120.0
#: seconds one step may take from putting its views to the frames being mapped
STEP_S = 60.0


def _listening(port: int) -> bool:
    """Whether something accepts TCP connections on loopback ``port``."""
    import socket

    with socket.socket() as sock:
        sock.settimeout(0.5)
        return sock.connect_ex(("127.0.0.1", port)) == 0


class LiveMapper:
    """A mapper process and the robot's edge process, driven step by step (a context manager).

    ``world_seed`` / ``world_preset``: the world the edge renders (the simulator's);
    ``chain``: the in-process edge chain whose settings and PCA basis the edge uses; ``cfg``:
    the policy's mapper config (:func:`apps.closed_loop.world_model.mapper_config`);
    ``band_m``: the costmap's z band; ``window_m``: half-size of the costmap around the robot;
    ``work``: a directory for the config files and the processes' logs."""

    renders_remotely = True

    def __init__(self, world_seed: int, world_preset: str, chain, cfg, band_m: tuple[float, float],
                 window_m: float, work: Path, robot: str = "sim", semantic: bool = True):
        import yaml

        from apps.demo import zenoh_env
        from common.config import to_dict
        from common.zenoh_session import free_tcp_port

        self.work, self.robot = Path(work), robot
        self.work.mkdir(parents=True, exist_ok=True)
        self.band, self.window, self.semantic = band_m, float(window_m), semantic
        if not semantic:   # geometry only: no ray may attach to a frontier (as LocalMapper does it)
            cfg = dataclasses.replace(cfg, search=dataclasses.replace(cfg.search, ray_radius_m=1e-9))
        (self.work / "mapper.yaml").write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))
        basis = self.work / "pca.npz"
        chain.pca.save(basis)
        self.endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        self._procs: list[tuple[str, subprocess.Popen, Any]]     # (name, process, its log file)
        self._env, self._procs = zenoh_env(), []
        self.sent = self.step = 0
        s = chain.cfg
        self._start("mapper", "mapper", "--mode", "router", "--listen", self.endpoint, "--config",
                    str(self.work / "mapper.yaml"), "rerun.file=", "snapshots.on_exit=false", "layers.rate_hz=0",
                    "queues.per_robot=1000")
        self._start("edge", "edge", "--connect", self.endpoint, f"robot={robot}", f"source.robot={robot}",
                    "source.kind=sim_camera", f"source.seed={world_seed}", f"source.preset={world_preset}",
                    f"source.resolution={s.resolution}x{s.resolution}", "source.hfov=90",
                    f"source.sky_depth={'nan' if s.sky_no_return else 'inf'}", f"encoder.kind={s.encoder}",
                    f"encoder.label_stride={s.label_stride}", f"pca.basis={basis}", f"pca.out_dim={s.pca_dim}",
                    f"publish.feature_codec={s.feature_codec}", "publish.lossless=true", "publish.rate_hz=0")
        try:
            self._connect()
        except BaseException:
            self.close()
            raise

    def _start(self, name: str, *args: str) -> None:
        log = open(self.work / f"{name}.log", "wb")
        p = subprocess.Popen([sys.executable, "-m", "apps.cli", *args], stdout=log, stderr=subprocess.STDOUT,
                             env=self._env)
        self._procs.append((name, p, log))

    def _connect(self) -> None:
        from common.zenoh_session import ZenohConfig
        from query_client.client import Client

        port = int(self.endpoint.rsplit(":", 1)[1])
        wait_for(lambda: self._alive() and _listening(port), START_S, what="the mapper's Zenoh router",
                 error=RuntimeError)
        self.client = Client(ZenohConfig(mode="client", connect=[self.endpoint]))
        self._views = self.client.session.declare_publisher(self.client.keys.sim_views(self.robot))
        # zenoh's stub types matching_status as bool; it returns a MatchingStatus
        wait_for(lambda: self._alive() and self._views.matching_status.matching,  # type: ignore[attr-defined]
                 START_S, what="the mapper and the edge's sim camera", error=RuntimeError)

    def _alive(self) -> bool:
        for name, p, _ in self._procs:
            if p.poll() is not None:
                raise RuntimeError(f"the {name} process exited with {p.returncode}: {self._tail(name)}")
        return True

    def _tail(self, name: str) -> str:
        text = (self.work / f"{name}.log").read_text(errors="replace").strip().splitlines()
        return " | ".join(text[-5:])

    def sense(self, poses: list[np.ndarray]) -> None:
        """Have the edge render and send ``poses`` (camera-to-world), and wait until the mapper
        has mapped or dropped every frame sent so far."""
        from common.messages import encode_sim_views

        self._views.put(encode_sim_views(self.step, np.stack(poses)))
        self.step += 1
        self.sent += len(poses)
        wait_for(self._caught_up, STEP_S, every=0.02, what=f"{self.sent} frames mapped", error=RuntimeError)

    def _caught_up(self) -> bool:
        self._alive()
        r = self.client.stats(timeout=5.0).get("robots", {}).get(self.robot, {})
        return int(r.get("mapped", 0)) + int(r.get("dropped", 0)) >= self.sent

    def mapped(self) -> int:
        """Frames of this robot the mapper has mapped."""
        return int(self.client.stats(timeout=5.0).get("robots", {}).get(self.robot, {}).get("mapped", 0))

    def observe(self, targets: list[str], at: np.ndarray, max_goals: int = 96, threshold: float = 0.5,
                semantic: bool = True, z_band: tuple[float, float] | None = None) -> Observation:
        """As :meth:`apps.closed_loop.world_model.LocalMapper.observe`, from the live mapper."""
        t = time.perf_counter()
        rep = self.client.search(list(targets), from_xyz=[float(v) for v in at], threshold=threshold,
                                 max_goals=max_goals, max_instances=20,
                                 z_band=None if z_band is None else [float(v) for v in z_band], timeout=30.0)
        ms = (time.perf_counter() - t) * 1e3
        lo, hi = np.asarray(at[:2]) - self.window, np.asarray(at[:2]) + self.window
        occ = self.client.occupancy_slice(lo, hi, self.band, timeout=30.0)
        goals = rep.look_next
        if not semantic:
            goals = [dict(g, score=0.0, target=None) for g in goals]
        return Observation(list(rep.found), goals, np.asarray(occ.states, np.int8), np.asarray(occ.origin, np.float64),
                           float(occ.cell_m), [], ms,
                           list((rep.beyond or {}).get("estimates", [])) if semantic else [])

    def close(self) -> None:
        """Stop the edge, then the mapper (SIGINT, then SIGKILL after a bounded wait)."""
        client = getattr(self, "client", None)
        if client is not None:
            client.close()
        for _, p, log in reversed(self._procs):
            stop_process(p, timeout=20)
            log.close()
        self._procs.clear()

    def __enter__(self) -> LiveMapper:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
