"""Row rasterisation of search shapes (the fast scoring path) = the block-test path, exactly."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from apps.evaluation import raster, shapes
from common.config import merge

pytestmark = pytest.mark.usefixtures("torch_two_threads")


def _case(rng, vox):
    lo = rng.integers(-30, 10, 3)
    dims = rng.integers(4, 30, 3)
    g = np.stack(np.meshgrid(*[np.arange(a, a + n) for a, n in zip(lo, dims, strict=True)], indexing="ij"),
                 -1).reshape(-1, 3)
    ijk = g[rng.random(len(g)) < 0.6]
    n = 10
    # origins on voxel centres, on voxel corners and anywhere, partly outside the box
    o = (rng.integers(lo - 5, lo + dims + 5, (n, 3)) + rng.choice([0.0, 0.5, 0.25], (n, 1))) * vox
    o[-1] = rng.uniform(lo - 5, lo + dims + 5) * vox
    d = rng.normal(size=(n, 3))
    d[:4] = [[1, 0, 0], [0, -1, 0], [0, 0, 1], [1, 1, 0]]    # axis-aligned; a generator along x at 45°
    return ijk, o, d


@pytest.mark.parametrize("seed", range(8))
def test_cones_balls_pyramids_equal_block_path(seed):
    rng = np.random.default_rng(seed)
    vox = [1.0, 0.5, 0.05, 0.3][seed % 4]
    ijk, o, d = _case(rng, vox)
    grid = raster.RowGrid.around(ijk, vox)
    cells = grid.cells(ijk)
    xyz = (ijk.astype(np.float64) + 0.5) * vox
    for alpha in (45.0, [10.0, 30.0, 60.0, 80.0, 89.0][seed % 5]):
        want = shapes.cone_counts(xyz, o, d, alpha).numpy()
        np.testing.assert_array_equal(raster.cone_counts(grid, o, d, alpha, cells), want)
        assert want.max() > 0 or alpha != 45.0
    r = rng.uniform(0.5, 8, len(o)) * vox
    r[:3] = np.round(r[:3] / vox) * vox                      # voxel centres exactly on the sphere
    want = shapes.ball_counts(xyz, o, r).numpy()
    np.testing.assert_array_equal(raster.ball_counts(grid, o, r, cells), want)
    for s, alpha in ((4, 45.0), (5, 45.0), (2, 30.0)):
        want = shapes.reference_cone_counts(xyz, o, d, vox, s, alpha).numpy()
        np.testing.assert_array_equal(raster.reference_cone_counts(grid, o, d, s, alpha, cells=cells), want)


def test_dense_grid_output_and_bad_input():
    ijk = np.array([[0, 0, 0], [3, 1, 1]])
    grid = raster.RowGrid.around(ijk, 1.0)
    assert grid.axis == 0 and grid.n_rows == 4 and grid.row_len == 4
    dense = raster.cone_counts(grid, [[-0.5, 0.5, 0.5]], [[1.0, 0, 0]], 30.0)
    assert dense.shape == (4, 2, 2)
    np.testing.assert_array_equal(dense[:, 0, 0], [1, 1, 1, 1])    # the axis row (y = z = 0.5) lies inside
    assert dense[:, 1, 1].sum() < 4
    np.testing.assert_array_equal(raster.cone_counts(grid, [[-0.5, 0.5, 0.5]], [[1.0, 0, 0]], 30.0, grid.cells(ijk)),
                                  [dense[0, 0, 0], dense[3, 1, 1]])
    with pytest.raises(ValueError, match="half-angle"):
        raster.cone_counts(grid, [[0, 0, 0]], [[1.0, 0, 0]], 90.0)
    with pytest.raises(ValueError, match="outside"):
        grid.cells(np.array([[5, 0, 0]]))
    assert raster.ball_counts(grid, np.empty((0, 3)), np.empty(0), grid.cells(ijk)).tolist() == [0, 0]


# ----------------------------------------------------------------------------- whole runs
@pytest.fixture(scope="module")
def world():
    from synthetic_world import World
    return World.generate(0)


@pytest.mark.parametrize("shape", ["true", "reference"])
def test_run_raster_equals_blocks(tmp_path, world, shape):
    """Whole benchmark, both counting paths: every step row (TP/FP/FN/TN …) is identical."""
    from apps.evaluation.srchvol import SrchvolConfig, run_srchvol

    out = {}
    for scoring in ("raster", "blocks"):
        cfg = merge(SrchvolConfig(), dict(source=dict(n_frames=12, resolution="40x40"), every=6, depth_limits=[10.0],
                                          gt_range=25.0, progress=False, plots=False, cone_shape=shape,
                                          scoring=scoring, map={"max_rays_per_frame": 300},
                                          methods=["rayfronts", "spherical_semfronts", "unidirectional_semfronts"]))
        run_srchvol(cfg, tmp_path / scoring, world=world)
        out[scoring] = json.loads((tmp_path / scoring / "steps.json").read_text())
    assert out["raster"] == out["blocks"]
    assert any(r["evidence"] for r in out["raster"] if r["method"] == "rayfronts")
    assert any(r["evidence"] for r in out["raster"] if r["method"] == "spherical_semfronts")


def test_wide_cones_fall_back_to_blocks(tmp_path, world):
    from apps.evaluation.srchvol import SrchvolConfig, run_srchvol

    cfg = merge(SrchvolConfig(), dict(source=dict(n_frames=6, resolution="32x32"), every=6, depth_limits=[10.0],
                                      gt_range=20.0, progress=False, plots=False, cone_half_angle=100.0,
                                      methods=["rayfronts"]))
    s = run_srchvol(cfg, tmp_path, world=world)
    assert 0.0 <= s["10m"]["rayfronts"]["scv_auc"] <= 1.0
    assert math.isclose(json.loads((tmp_path / "run_info.json").read_text())["cone_half_angle_deg"], 100.0)
