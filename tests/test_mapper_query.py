"""Queries (top-k, softmax, whole-map denoising) and search-volume rasterisation."""
import math

import torch

from semantic_map.query import run_query
from semantic_map.search_volume import (
    ball_membership_counts,
    cone_membership_counts,
    frontier_ball_radii,
    search_volume_mask,
)


def test_query_topk_softmax_denoise_vs_bruteforce():
    g = torch.Generator().manual_seed(0)
    vf = torch.randn(5000, 16, generator=g).half()
    vx = torch.randn(5000, 3, generator=g)
    rf, ro, rd = torch.randn(40, 16, generator=g), torch.randn(40, 3, generator=g), torch.randn(40, 3, generator=g)
    q = torch.randn(3, 16, generator=g)
    res = run_query(q, vf, vx, rf, ro, rd, top_k=7, chunk=999)
    ref = torch.nn.functional.normalize(q, dim=1) @ torch.nn.functional.normalize(vf.float(), dim=1).T
    torch.testing.assert_close(res.voxel_sim, ref, atol=1e-5, rtol=1e-5)
    for i in range(3):
        assert torch.equal(res.top_voxels[i].index, torch.topk(res.voxel_sim[i], 7).indices)
        torch.testing.assert_close(res.top_voxels[i].xyz, vx[res.top_voxels[i].index])
    assert torch.equal(res.voxel_labels, ref.argmax(0))
    # softmax over queries + denoising over the whole layer (not per chunk)
    sm = torch.softmax(3 * ref, 0)
    mx = sm.max(1).values.sort().values
    thr = float(mx[0] + mx[1]) / 2  # disables exactly the weakest query
    res = run_query(q, vf, vx, rf, ro, rd, softmax=True, temperature=3.0, denoise=thr, threshold=0.6, chunk=500)
    dis = sm.max(1).values < thr
    assert torch.equal(res.voxel_disabled, dis) and int(dis.sum()) == 1
    sm2 = sm.masked_fill(dis[:, None], 0)
    best, lab = sm2.max(0)
    lab[best < 0.6] = -1
    assert torch.equal(res.voxel_labels, lab)


def test_custom_similarity_is_used():
    vf = torch.eye(4)
    calls = []

    def sim(f, q):
        calls.append(f.shape[0])
        return q[:, :4] @ f.T

    res = run_query(torch.tensor([[0.0, 2.0, 0, 0, 9.0]]), vf, torch.zeros(4, 3), vf[:0], torch.zeros(0, 3),
                    torch.zeros(0, 3), similarity=sim, top_k=1, chunk=3)
    assert calls[:2] == [3, 1] and res.top_voxels[0].index.tolist() == [1]


def test_cone_counts_vs_bruteforce():
    g = torch.Generator().manual_seed(1)
    vox = torch.randint(-20, 20, (6000, 3), generator=g).double() + 0.5
    o = torch.randn(25, 3, generator=g, dtype=torch.float64) * 5
    d = torch.nn.functional.normalize(torch.randn(25, 3, generator=g, dtype=torch.float64), dim=1)
    for ha, near, far in ((20.0, 0.0, math.inf), (45.0, 2.0, 15.0)):
        c = cone_membership_counts(vox, o, d, ha, near=near, far=far, chunk=4096)
        v = vox[:, None] - o[None]
        t = (v * d[None]).sum(2)
        inside = (t >= near) & (t <= far) & (t >= v.norm(dim=2) * math.cos(math.radians(ha)))
        assert torch.equal(c, inside.sum(1))
        assert int(c.sum()) > 0
    w = torch.rand(25, generator=g, dtype=torch.float64)
    cw = cone_membership_counts(vox, o, d, 30.0, weights=w)
    v = vox[:, None] - o[None]
    t = (v * d[None]).sum(2)
    inside = (t >= 0) & (t >= v.norm(dim=2) * math.cos(math.radians(30)))
    torch.testing.assert_close(cw, (inside.double() * w).sum(1))


def test_ball_counts_and_radii():
    g = torch.Generator().manual_seed(2)
    vox = torch.rand(3000, 3, generator=g, dtype=torch.float64) * 20
    c = torch.rand(10, 3, generator=g, dtype=torch.float64) * 20
    r = frontier_ball_radii(c, 2.0)
    dd = torch.cdist(c, c) + torch.diag(torch.full((10,), math.inf, dtype=torch.float64))
    torch.testing.assert_close(r, dd.min(1).values)
    cnt = ball_membership_counts(vox, c, r)
    assert torch.equal(cnt, (torch.cdist(vox, c) <= r[None]).sum(1))
    m = search_volume_mask(cnt, 0.05)
    assert torch.equal(m, cnt.double() / cnt.max() > 0.05)
    assert frontier_ball_radii(c[:1], 2.0).tolist() == [2.0]
