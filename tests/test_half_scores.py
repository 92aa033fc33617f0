"""The C++ float16 query product (semantic_map.kernels.half_scores) against a float64 brute
force, against its torch twin (the query copy with the kernels disabled), and the per-row
independence the score caches rely on (a row scores the same in any subset and any thread
split)."""
import platform

import numpy as np
import pytest
import torch

from semantic_map import kernels
from semantic_map.query_copy import SCORE_ATOL, QueryCopy


def _cpu_flags() -> set[str]:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("flags"):
                return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


@pytest.fixture(autouse=True)
def _kernel_here():
    """The kernel must run on an x86-64 CPU with AVX2, FMA and F16C (CI's): a module built
    without it fails there; elsewhere (an ARM base station) the torch path is the only one."""
    if platform.machine() in ("x86_64", "AMD64") and {"avx2", "fma", "f16c"} <= _cpu_flags():
        assert kernels.available(), kernels.IMPORT_ERROR
        assert kernels.half_scores_enabled(torch.zeros((1, 8), dtype=torch.float16))
    else:                                                   # pragma: no cover - not CI's machine
        pytest.skip("half_scores needs an x86-64 CPU with AVX2/FMA/F16C")


def _rows(n: int, d: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    h = (torch.randn((n, d), generator=g) * 0.4).clamp(-1, 1).to(torch.float16)
    q = torch.randn(d, generator=g)
    a = torch.rand(n, generator=g) * 3 + 0.1
    b = torch.rand(n, generator=g)
    return h, q, a, b


@pytest.mark.parametrize("n,d", [(1, 3), (3, 8), (7, 100), (1001, 37), (70_001, 100)])
def test_half_scores_equal_float64_brute_force(n, d):
    h, q, a, b = _rows(n, d, seed=n + d)
    for bb, qm in ((b, -0.37), (None, 0.0)):
        got = kernels.half_scores(h, q, a, bb, qm, threads=2)
        ref = (h.double() @ q.double()) * a.double() + (0.0 if bb is None else qm * bb.double())
        scale = float((h.double().abs() @ q.double().abs() * a.double()).max()) + 1.0
        assert got.dtype == torch.float32 and got.shape == (n,)
        # float32 sums of exact float16 × float32 products: rounding only, no float16 step
        assert float((got.double() - ref).abs().max()) <= 1e-6 * scale


def test_half_scores_per_row_whatever_the_subset_or_threads():
    h, q, a, b = _rows(200_003, 45, seed=3)
    whole = kernels.half_scores(h, q, a, b, 0.25, threads=1)
    for t in (2, 3, 8):
        assert torch.equal(kernels.half_scores(h, q, a, b, 0.25, threads=t), whole)
    rows = torch.randperm(h.shape[0], generator=torch.Generator().manual_seed(4))[:77_777]
    sub = kernels.half_scores(h[rows], q, a[rows], b[rows], 0.25, threads=2)
    assert torch.equal(sub, whole[rows])


def test_half_scores_reject_wrong_shapes():
    h, q, a, b = _rows(10, 16, seed=5)
    with pytest.raises(ValueError, match="q must be"):
        kernels.half_scores(h, q[:8], a, b, 0.0, threads=1)
    with pytest.raises(ValueError, match="a and out"):
        kernels.half_scores(h, q, a[:5], b, 0.0, threads=1)
    with pytest.raises(ValueError, match="b must be"):
        kernels.half_scores(h, q, a, b[:5], 0.0, threads=1)


def test_query_copy_kernel_and_torch_paths_agree():
    """The query copy (PCA space with a mean term) scored by the kernel and by torch's float16
    product: both within SCORE_ATOL of the float64 cosine, the kernel closer."""
    from apps.bench.query import _space, build_map

    fs = _space(32)
    _, mp = build_map(40_000, 32, 100, fs, seed=6)
    q = torch.randn((2, fs.lang_dim), generator=torch.Generator().manual_seed(7))
    m, v = fs.pca.torch_basis("cpu", torch.float32)
    x = mp.voxels().features.double() @ v.double().T + m.double()
    ref = ((q.double() / q.double().norm(dim=1, keepdim=True)) @ (x / x.norm(dim=1, keepdim=True)).T).numpy()
    fast = QueryCopy().take(mp, 0).prepared(fs)[0].similarity(q, use_cache=False).numpy()
    with kernels.disabled():
        slow = QueryCopy().take(mp, 0).prepared(fs)[0].similarity(q, use_cache=False).numpy()
    e_fast, e_slow = np.abs(fast - ref).max(), np.abs(slow - ref).max()
    assert e_fast <= SCORE_ATOL and e_slow <= SCORE_ATOL, (e_fast, e_slow)
    assert e_fast < e_slow                                  # no float16 rounding of query or sum
    assert not np.array_equal(fast, slow)                   # the two paths really ran
