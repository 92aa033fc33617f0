"""The paper's claim on the synthetic world, with the simulated ViT-like encoder (not the
ground-truth label features): RayFronts' SCVR AUC beats each frontier baseline (Spherical and
Unidirectional Semantic Frontiers) at 10 m and 20 m depth, on several small seeds."""
import pytest

from apps.evaluation.srchvol import SrchvolConfig, run_srchvol
from common.config import merge

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("torch_two_threads")]

SEEDS = (0, 1, 2)


@pytest.mark.parametrize("seed", SEEDS)
def test_rayfronts_beats_frontier_baselines_sim_encoder(tmp_path, seed):
    cfg = merge(SrchvolConfig(), dict(source=dict(seed=seed, n_frames=60, resolution="64x64"),
                                      depth_limits=[10.0, 20.0],
                                      methods=["rayfronts", "spherical_semfronts", "unidirectional_semfronts"],
                                      every=5, progress=False, plots=False, encoder=dict(kind="sim")))
    out = run_srchvol(cfg, tmp_path)
    for dk in ("10m", "20m"):
        rf = out[dk]["rayfronts"]["scvr_auc"]
        for base in ("spherical_semfronts", "unidirectional_semfronts"):
            assert rf > out[dk][base]["scvr_auc"], (seed, dk, base, out[dk])
