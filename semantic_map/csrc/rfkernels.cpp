// semantic_map._rfkernels: small CPU kernels for the mapper's hot loops (no OpenVDB).
//
// Every kernel has a pure-torch twin in mapper/*.py that gives the same result; the
// Python side (semantic_map/kernels.py) picks the kernel when this module imports. Kernels take
// C-contiguous CPU numpy arrays / torch tensors (DLPack), release the GIL, run on one
// thread (half_scores: on as many as it is given) and return numpy arrays (zero-copy for
// torch.from_numpy).
//
// * unique_i64(keys) -> (sorted unique, inverse, counts): torch.unique(sorted=True,
//   return_inverse=True, return_counts=True) by open-addressing hashing (O(N) + sort of
//   the unique keys), not by sorting all N keys.
// * associate_rays(...) + argmin_cost(...) (ray_association.cpp): for rays (o, d, length)
//   and coarse frontier cells of size beta, the association of semantic_map.ray_frontiers
//   (test t > 0, |p - o - t d| <= beta, |p - o| <= max_dist (and >= 2 beta with
//   reject_close); per-ray normalised cost; argmin) with bit-identical results;
//   associate_rays_fan(...) finds the same pairs for rays from a few origins (a ray block's
//   cameras) by binning their directions instead of walking them.
// * group_pairs(group, idx, wt, n_groups, n_src): the non-zeros of the (group x source)
//   sampling matrix of semantic_map.depth_geometry.aggregate_samples, as its bincount path;
//   sample_pairs(...) also computes the bilinear / nearest corners (_corners) itself.
// * segment_cells_unique(...): the unique cells of semantic_map.traversal.unique_cells (same
//   crossing enumeration and float32 arithmetic), hashed instead of a dense mask / sort.
// * voxel_keys_f32/_f64(xyz, vox): packed keys of floor(xyz / vox) (float64 division).
// * surface_samples(...): semantic surface points and the unique occupied voxels of a
//   frame (semantic_map.depth_geometry), with the torch code's float64 operations.
// * components_26_sorted(keys): 26-connected components of a voxel set given as strictly
//   ascending packed keys (semantic_map.cell_keys layout), numbered 0..C-1 by each
//   component's lowest key, as planning.instances.connected_26's numpy path: union-find over
//   the 13 half-neighbours, found by one forward pointer per neighbouring (i, j) row (O(N));
//   on up to `threads` threads over spans of whole i-slabs, then the edges across the cuts.
// * instance_groups(keys, labels, conf, min_voxels): the kept groups of a labelled voxel set
//   (planning.instances.InstanceTracker.update's numpy group step): counting sort by group,
//   index sums / minima / maxima and max confidence per group.
// * cone_weighted_union(local, w, frames, o, d, range_m, cos2, threads): common.cones'
//   _weighted_union (the per-cone step of the sampled cone-union volume): each cone's lattice
//   points placed in the world, counted against every cone, weight / count summed; the same
//   tests in float64 (products summed in another order: equal up to rounding).
// * argsort_voxel_keys(keys, threads): np.argsort(keys, kind="stable") of packed voxel keys
//   and the keys in that order, by an LSD radix sort of the keys re-packed relative to their
//   smallest index per axis (when that fits 32 bits; else None and numpy sorts), on up to
//   `threads` threads (each pass: per-thread histograms, then each thread scatters its part).
// * half_scores(...) (half_scores.cpp): the query snapshot's float16 text-query product; the
//   one kernel that is not bit-identical to its torch twin (float32 instead of float16
//   rounding: within the documented score tolerance, closer to the exact cosine).

#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/tuple.h>

#include "half_scores.h"
#include "arrays.h"
#include "key_ids.h"
#include "ray_association.h"
#include "numpy_out.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numeric>
#include <stdexcept>
#include <thread>
#include <vector>

namespace nb = nanobind;
using rfk::KeyIds;
using namespace rfk::arrays;

namespace {



// rank[id] = position of keys[id] in ascending order
std::vector<int64_t> sorted_rank(const std::vector<int64_t>& keys, std::vector<int64_t>& order) {
    order.resize(keys.size());
    std::iota(order.begin(), order.end(), int64_t(0));
    std::sort(order.begin(), order.end(), [&](int64_t a, int64_t b) { return keys[a] < keys[b]; });
    std::vector<int64_t> rank(keys.size());
    for (size_t r = 0; r < order.size(); ++r) rank[order[r]] = int64_t(r);
    return rank;
}

nb::tuple unique_i64(I64In keys) {
    const size_t n = keys.shape(0);
    std::vector<int64_t> uniq, inverse(n), counts;
    {
        nb::gil_scoped_release release;
        const int64_t* k = keys.data();
        KeyIds ids(std::min<size_t>(n, 1 << 16));
        for (size_t i = 0; i < n; ++i) inverse[i] = ids.insert(k[i]);
        std::vector<int64_t> order;
        std::vector<int64_t> rank = sorted_rank(ids.keys(), order);
        const size_t u = order.size();
        uniq.resize(u);
        counts.assign(u, 0);
        for (size_t r = 0; r < u; ++r) uniq[r] = ids.keys()[order[r]];
        for (size_t i = 0; i < n; ++i) {
            inverse[i] = rank[inverse[i]];
            ++counts[inverse[i]];
        }
    }
    size_t u = uniq.size();
    return nb::make_tuple(to_numpy(std::move(uniq), {u}), to_numpy(std::move(inverse), {n}),
                          to_numpy(std::move(counts), {u}));
}

// Non-zeros of the sparse (group x source) weight matrix A of
// semantic_map.depth_geometry.aggregate_samples: entries (group[p], idx[p, c], wt[p, c]); returns
// (g, src, weight) for every distinct (g, src) with a non-zero sum, in ascending
// (g, src) order; each sum is accumulated in float32 in input order (as torch.bincount
// does). Entries are bucketed by group (counting sort, stable) and de-duplicated per
// group with a stamp array over sources, so the cost is O(P k + unique log).
nb::tuple group_pairs_core(const int64_t* g, const int64_t* ix, const float* w, size_t P, size_t k,
                           int64_t n_groups, int64_t n_src) {
    if (n_groups < 0 || n_src < 0) throw std::invalid_argument("n_groups and n_src must be >= 0");
    std::vector<int64_t> out_g, out_s;
    std::vector<float> out_w;
    {
        nb::gil_scoped_release release;
        std::vector<int64_t> start(size_t(n_groups) + 1, 0);
        for (size_t q = 0; q < P; ++q) {
            if (g[q] < 0 || g[q] >= n_groups) throw std::out_of_range("group index out of range");
            start[g[q] + 1] += int64_t(k);
        }
        for (int64_t b = 0; b < n_groups; ++b) start[b + 1] += start[b];
        // entries (source, weight) bucketed by group, input order kept within a group
        std::vector<int64_t> bsrc(P * k);
        std::vector<float> bw(P * k);
        {
            std::vector<int64_t> fill(start.begin(), start.end() - 1);
            for (size_t q = 0; q < P; ++q) {
                int64_t& f = fill[g[q]];
                for (size_t c = 0; c < k; ++c, ++f) {
                    const int64_t src = ix[q * k + c];
                    if (src < 0 || src >= n_src) throw std::out_of_range("source index out of range");
                    bsrc[f] = src;
                    bw[f] = w[q * k + c];
                }
            }
        }
        std::vector<int64_t> stamp(size_t(n_src), -1);
        std::vector<int32_t> slot(size_t(n_src), 0);
        std::vector<int64_t> srcs, order;
        std::vector<float> acc;
        out_g.reserve(P);
        out_s.reserve(P);
        out_w.reserve(P);
        for (int64_t b = 0; b < n_groups; ++b) {
            srcs.clear();
            acc.clear();
            for (int64_t e = start[b]; e < start[b + 1]; ++e) {
                const int64_t src = bsrc[e];
                if (stamp[src] != b) {
                    stamp[src] = b;
                    slot[src] = int32_t(srcs.size());
                    srcs.push_back(src);
                    acc.push_back(0.0f);
                }
                acc[slot[src]] += bw[e];
            }
            order.resize(srcs.size());
            std::iota(order.begin(), order.end(), int64_t(0));
            std::sort(order.begin(), order.end(), [&](int64_t x, int64_t y) { return srcs[x] < srcs[y]; });
            for (int64_t o : order) {
                if (acc[o] == 0.0f) continue;
                out_g.push_back(b);
                out_s.push_back(srcs[o]);
                out_w.push_back(acc[o]);
            }
        }
    }
    const size_t m = out_g.size();
    return nb::make_tuple(to_numpy(std::move(out_g), {m}), to_numpy(std::move(out_s), {m}),
                          to_numpy(std::move(out_w), {m}));
}

nb::tuple group_pairs(I64In group, nb::ndarray<const int64_t, nb::ndim<2>, nb::c_contig, nb::device::cpu> idx,
                      nb::ndarray<const float, nb::ndim<2>, nb::c_contig, nb::device::cpu> wt,
                      int64_t n_groups, int64_t n_src) {
    const size_t P = group.shape(0), k = idx.shape(1);
    if (idx.shape(0) != P || wt.shape(0) != P || wt.shape(1) != k)
        throw std::invalid_argument("group (P,), idx (P, k) and wt (P, k) disagree");
    return group_pairs_core(group.data(), idx.data(), wt.data(), P, k, n_groups, n_src);
}

// Source pixels and weights for sampling an (h, w) map at the centres of flat pixels of an
// (H, W) image: the float32 operations of semantic_map.depth_geometry._corners (align_corners
// False; bilinear with edge clamping, or nearest when `nearest` or the sizes are equal).
void corners(const int64_t* pix, size_t P, int64_t H, int64_t W, int64_t h, int64_t w, bool nearest,
             std::vector<int64_t>& idx, std::vector<float>& wt, size_t& k) {
    const float sx = float(double(w) / double(W)), sy = float(double(h) / double(H));
    const bool nn = nearest || (h == H && w == W);
    k = nn ? 1 : 4;
    idx.resize(P * k);
    wt.resize(P * k);
    const float wm = float(w - 1), hm = float(h - 1);
    for (size_t q = 0; q < P; ++q) {
        const int64_t p = pix[q];
        if (p < 0 || p >= H * W) throw std::out_of_range("pixel index out of range");
        const int64_t r = p / W, c = p - r * W;
        float x = (float(c) + 0.5f) * sx - 0.5f;
        float y = (float(r) + 0.5f) * sy - 0.5f;
        if (nn) {
            int64_t xi = int64_t(std::min(std::max(std::floor(x + 0.5f), 0.0f), wm));
            int64_t yi = int64_t(std::min(std::max(std::floor(y + 0.5f), 0.0f), hm));
            idx[q] = yi * w + xi;
            wt[q] = 1.0f;
            continue;
        }
        x = std::min(std::max(x, 0.0f), wm);
        y = std::min(std::max(y, 0.0f), hm);
        const int64_t x0 = int64_t(std::floor(x)), y0 = int64_t(std::floor(y));
        const int64_t x1 = std::min<int64_t>(x0 + 1, w - 1), y1 = std::min<int64_t>(y0 + 1, h - 1);
        const float fx = x - float(x0), fy = y - float(y0);
        const float gx = 1.0f - fx, gy = 1.0f - fy;
        idx[4 * q] = y0 * w + x0;
        idx[4 * q + 1] = y0 * w + x1;
        idx[4 * q + 2] = y1 * w + x0;
        idx[4 * q + 3] = y1 * w + x1;
        wt[4 * q] = gx * gy;
        wt[4 * q + 1] = fx * gy;
        wt[4 * q + 2] = gx * fy;
        wt[4 * q + 3] = fx * fy;
    }
}

// group_pairs of the sampling matrix of flat pixels `pix` of an (H, W) image on an (h, w)
// map, the corners computed as semantic_map.depth_geometry._corners does.
nb::tuple sample_pairs(I64In group, I64In pix, int64_t H, int64_t W, int64_t h, int64_t w, bool nearest,
                       int64_t n_groups) {
    const size_t P = pix.shape(0);
    if (group.shape(0) != P) throw std::invalid_argument("group and pix differ in length");
    if (H < 1 || W < 1 || h < 1 || w < 1) throw std::invalid_argument("image sizes must be >= 1");
    std::vector<int64_t> idx;
    std::vector<float> wt;
    size_t k = 0;
    {
        nb::gil_scoped_release release;
        corners(pix.data(), P, H, W, h, w, nearest, idx, wt, k);
    }
    return group_pairs_core(group.data(), idx.data(), wt.data(), P, k, n_groups, h * w);
}

constexpr int64_t kIdxLo = -(int64_t(1) << 20), kIdxHi = (int64_t(1) << 20) - 1;

inline int64_t pack_key(int64_t i, int64_t j, int64_t k) {
    constexpr int64_t off = int64_t(1) << 20;
    return ((i + off) << 42) | ((j + off) << 21) | (k + off);
}

struct Range {
    int64_t lo = std::numeric_limits<int64_t>::max(), hi = std::numeric_limits<int64_t>::min();
    void add(int64_t v) {
        lo = std::min(lo, v);
        hi = std::max(hi, v);
    }
    bool ok() const { return lo > hi || (lo >= kIdxLo && hi <= kIdxHi); }
};

// Packed keys (semantic_map.cell_keys) of voxel_index(xyz, vox) = floor(double(xyz) / vox), plus the
// smallest / largest index (so that Python raises semantic_map.cell_keys' error when out of range).
template <typename T>
nb::tuple voxel_keys_impl(const T* x, size_t n, double vox) {
    std::vector<int64_t> keys(n);
    Range rg;
    {
        nb::gil_scoped_release release;
        for (size_t q = 0; q < n; ++q) {
            int64_t a = int64_t(std::floor(double(x[3 * q]) / vox));
            int64_t b = int64_t(std::floor(double(x[3 * q + 1]) / vox));
            int64_t c = int64_t(std::floor(double(x[3 * q + 2]) / vox));
            rg.add(a); rg.add(b); rg.add(c);
            keys[q] = pack_key(a, b, c);
        }
    }
    return nb::make_tuple(to_numpy(std::move(keys), {n}), rg.lo, rg.hi);
}

using F32x3In = nb::ndarray<const float, nb::shape<-1, 3>, nb::c_contig, nb::device::cpu>;

nb::tuple voxel_keys_f64(F64x3In xyz, double vox) { return voxel_keys_impl(xyz.data(), xyz.shape(0), vox); }
nb::tuple voxel_keys_f32(F32x3In xyz, double vox) { return voxel_keys_impl(xyz.data(), xyz.shape(0), vox); }

// Surface samples of a depth frame, as semantic_map.depth_geometry computes them in torch:
// z = double(depth[pix]); points = float32(origin + D[pix] * z); occupied samples
// origin + D[pix] * (z + offs[k]) for z + offs[k] > 0 -> sorted unique packed voxel keys.
nb::tuple surface_samples(F64In origin, F64x3In D, F32In depth, I64In pix, F64In offs, double vox) {
    if (origin.shape(0) != 3) throw std::invalid_argument("origin must have 3 values");
    if (D.shape(0) != depth.shape(0)) throw std::invalid_argument("D and depth must have one row per pixel");
    if (!(vox > 0)) throw std::invalid_argument("vox must be > 0");
    const size_t P = pix.shape(0), T = offs.shape(0), HW = depth.shape(0);
    std::vector<float> pts(3 * P);
    std::vector<int64_t> uniq;
    Range rg;
    {
        nb::gil_scoped_release release;
        const double o[3] = {origin.data()[0], origin.data()[1], origin.data()[2]};
        const double* Dp = D.data();
        const float* dp = depth.data();
        const int64_t* px = pix.data();
        const double* of = offs.data();
        KeyIds ids(std::min<size_t>(P * T, 1 << 16));
        for (size_t q = 0; q < P; ++q) {
            const int64_t i = px[q];
            if (i < 0 || size_t(i) >= HW) throw std::out_of_range("pixel index out of range");
            const double z = double(dp[i]);
            const double* dv = Dp + 3 * i;
            for (int a = 0; a < 3; ++a) {
                const double m = dv[a] * z;
                pts[3 * q + a] = float(o[a] + m);
            }
            for (size_t k = 0; k < T; ++k) {
                const double zs = z + of[k];
                if (!(zs > 0)) continue;
                int64_t c[3];
                for (int a = 0; a < 3; ++a) {
                    const double m = dv[a] * zs;
                    c[a] = int64_t(std::floor((o[a] + m) / vox));
                    rg.add(c[a]);
                }
                ids.insert(pack_key(c[0], c[1], c[2]));
            }
        }
        uniq = ids.keys();
        std::sort(uniq.begin(), uniq.end());
    }
    const size_t u = uniq.size();
    return nb::make_tuple(to_numpy(std::move(pts), {P, size_t(3)}), to_numpy(std::move(uniq), {u}), rg.lo, rg.hi);
}

// Sorted unique packed keys of every cell touched by segments o[i] -> e[i] (float64 world),
// the exact crossing enumeration of semantic_map.traversal._chunk_cells with its float32
// arithmetic: segments in chunks [lo, hi) with an integer base cell per chunk, coordinates
// relative to the base; a flagged segment (exclude_end) drops its end cell. Returns
// (keys, smallest index, largest index).
nb::tuple segment_cells_unique(F64x3In o, F64x3In e, double cell, I64In chunk_lo, I64In chunk_hi,
                               I64x3In chunk_base, nb::ndarray<const bool, nb::ndim<1>, nb::c_contig, nb::device::cpu> exclude_end,
                               bool include_start) {
    const size_t N = o.shape(0), C = chunk_lo.shape(0);
    if (e.shape(0) != N) throw std::invalid_argument("origins and ends differ in length");
    if (chunk_hi.shape(0) != C || chunk_base.shape(0) != C) throw std::invalid_argument("chunk arrays disagree");
    const bool has_ex = exclude_end.shape(0) > 0;
    if (has_ex && exclude_end.shape(0) != N) throw std::invalid_argument("exclude_end must be empty or (N,)");
    if (!(cell > 0)) throw std::invalid_argument("cell must be > 0");
    std::vector<int64_t> uniq;
    Range rg;
    {
        nb::gil_scoped_release release;
        const double* op = o.data();
        const double* ep = e.data();
        const bool* ex = exclude_end.data();
        const float cf = float(cell);
        KeyIds ids(1 << 14);
        for (size_t ch = 0; ch < C; ++ch) {
            const int64_t lo = chunk_lo.data()[ch], hi = chunk_hi.data()[ch];
            if (lo < 0 || hi > int64_t(N) || lo > hi) throw std::out_of_range("chunk bounds out of range");
            const int64_t* B = chunk_base.data() + 3 * ch;
            const double bf[3] = {double(B[0]) * cell, double(B[1]) * cell, double(B[2]) * cell};
            for (int64_t i = lo; i < hi; ++i) {
                float orel[3], diff[3];
                int64_t sc[3], fc[3];
                for (int a = 0; a < 3; ++a) {
                    const double ov = op[3 * i + a], evv = ep[3 * i + a];
                    orel[a] = float(ov - bf[a]);
                    const float erel = float(evv - bf[a]);
                    diff[a] = erel - orel[a];
                    sc[a] = int64_t(std::floor(ov / cell)) - B[a];
                    fc[a] = int64_t(std::floor(evv / cell)) - B[a];
                }
                const bool drop_end = has_ex && ex[i];
                auto emit = [&](int64_t x, int64_t y, int64_t z) {
                    if (drop_end && x == fc[0] && y == fc[1] && z == fc[2]) return;
                    x += B[0]; y += B[1]; z += B[2];
                    rg.add(x); rg.add(y); rg.add(z);
                    ids.insert(pack_key(x, y, z));
                };
                if (include_start) emit(sc[0], sc[1], sc[2]);
                for (int a = 0; a < 3; ++a) {
                    const int64_t stp = fc[a] - sc[a];
                    if (stp == 0) continue;
                    const int64_t sg = stp > 0 ? 1 : -1, cnt = stp > 0 ? stp : -stp;
                    const int b1 = (a + 1) % 3, b2 = (a + 2) % 3;
                    for (int64_t m = 1; m <= cnt; ++m) {
                        const int64_t entered = sc[a] + m * sg;
                        const int64_t plane = entered + (sg < 0 ? 1 : 0);
                        const float num = float(plane) * cf - orel[a];
                        const float t = num / diff[a];
                        int64_t c[3];
                        c[a] = entered;
                        const float u1 = t * diff[b1], u2 = t * diff[b2];
                        c[b1] = int64_t(std::floor((orel[b1] + u1) / cf));
                        c[b2] = int64_t(std::floor((orel[b2] + u2) / cf));
                        emit(c[0], c[1], c[2]);
                    }
                }
            }
        }
        uniq = ids.keys();
        std::sort(uniq.begin(), uniq.end());
    }
    const size_t u = uniq.size();
    return nb::make_tuple(to_numpy(std::move(uniq), {u}), rg.lo, rg.hi);
}

// 26-connected components of strictly ascending packed voxel keys (file comment).
nb::ndarray<nb::numpy, int64_t> components_26_sorted(I64In keys, int threads) {
    const size_t n = keys.shape(0);
    std::vector<int64_t> label(n);
    {
        nb::gil_scoped_release release;
        const int64_t* k = keys.data();
        for (size_t p = 1; p < n; ++p)
            if (k[p] <= k[p - 1]) throw std::invalid_argument("components_26_sorted: keys must be strictly ascending");
        constexpr int64_t off = int64_t(1) << 20, mask = (int64_t(1) << 21) - 1;
        std::vector<int64_t> parent(n);
        std::iota(parent.begin(), parent.end(), int64_t(0));
        auto find = [&](int64_t x) {
            while (parent[x] != x) {
                parent[x] = parent[parent[x]];
                x = parent[x];
            }
            return x;
        };
        // p's root is found once and kept (rp) while its later neighbours are joined to it
        auto join = [&](int64_t& rp, int64_t q) {
            const int64_t rq = find(q);
            if (rq < rp) {
                parent[rp] = rq;
                rp = rq;
            } else if (rp < rq) {
                parent[rq] = rp;
            }
        };
        // join each voxel p in [p_lo, p_hi) to its half-neighbours q in [q_lo, q_hi); spans of
        // whole i-slabs touch disjoint parents, so they run side by side
        auto unite_span = [&](size_t p_lo, size_t p_hi, size_t q_lo, size_t q_hi) {
            const int rows[4][2] = {{0, 1}, {1, -1}, {1, 0}, {1, 1}};   // (di, dj) of the half-neighbour rows
            size_t ptr[4] = {q_lo, q_lo, q_lo, q_lo};
            for (size_t p = p_lo; p < p_hi; ++p) {      // signed voxel indices, as pack_key takes them
                const int64_t a = (k[p] >> 42) - off, b = ((k[p] >> 21) & mask) - off, c = (k[p] & mask) - off;
                int64_t rp = find(int64_t(p));
                if (c < kIdxHi && p + 1 < q_hi && p + 1 >= q_lo && k[p + 1] == k[p] + 1) join(rp, int64_t(p + 1));
                for (int r = 0; r < 4; ++r) {
                    const int64_t a2 = a + rows[r][0], b2 = b + rows[r][1];
                    if (a2 > kIdxHi || b2 < kIdxLo || b2 > kIdxHi) continue;
                    const int64_t lo = pack_key(a2, b2, std::max(c - 1, kIdxLo));
                    const int64_t hi = pack_key(a2, b2, std::min(c + 1, kIdxHi));
                    size_t q = ptr[r];
                    while (q < q_hi && k[q] < lo) ++q;
                    ptr[r] = q;
                    for (; q < q_hi && k[q] <= hi; ++q) join(rp, int64_t(q));
                }
            }
        };
        // spans: about n / T voxels each, cut where the i index changes
        const size_t T = std::max<size_t>(1, std::min<size_t>(size_t(std::max(threads, 1)), n / 65536));
        std::vector<size_t> cut{0};
        for (size_t t = 1; t < T; ++t) {
            size_t m = std::max(cut.back() + 1, t * n / T);
            while (m < n && (k[m] >> 42) == (k[m - 1] >> 42)) ++m;
            if (m < n) cut.push_back(m);
        }
        cut.push_back(n);
        std::vector<std::thread> pool;
        for (size_t s = 1; s + 1 < cut.size(); ++s) pool.emplace_back(unite_span, cut[s], cut[s + 1], cut[s], cut[s + 1]);
        unite_span(cut[0], cut[1], cut[0], cut[1]);
        for (auto& th : pool) th.join();
        for (size_t s = 1; s + 1 < cut.size(); ++s) {   // the edges across a cut: last slab before it -> after it
            size_t first = cut[s] - 1;
            while (first > cut[s - 1] && (k[first - 1] >> 42) == (k[cut[s] - 1] >> 42)) --first;
            unite_span(first, cut[s], cut[s], cut[s + 1]);
        }
        int64_t next = 0;
        for (size_t p = 0; p < n; ++p) {
            const int64_t r = find(int64_t(p));
            label[p] = r == int64_t(p) ? next++ : label[r];
        }
    }
    return to_numpy(std::move(label), {n});
}

// Instances of a labelled voxel set (planning.instances.InstanceTracker.update's group step):
// keys strictly ascending, labels from components_26_sorted (0..C-1), conf in key order.
// Groups of at least min_voxels are kept and renumbered 0..G-1 in label order. Returns
// (kept: positions in key order of the kept voxels, their new labels, grouped: the kept keys
// ordered by group then key, counts, index sums (G, 3), minima (G, 3), maxima (G, 3),
// max conf (G,)), as the numpy path computes them.
nb::tuple instance_groups(I64In keys, I64In labels, F64In conf, int64_t min_voxels) {
    const size_t n = keys.shape(0);
    if (labels.shape(0) != n || conf.shape(0) != n) throw std::invalid_argument("instance_groups: lengths differ");
    std::vector<int64_t> kept, klab, grouped, counts, isum, imin, imax;
    std::vector<double> cmax;
    {
        nb::gil_scoped_release release;
        const int64_t* k = keys.data();
        const int64_t* lab = labels.data();
        const double* c = conf.data();
        int64_t n_lab = 0;
        for (size_t p = 0; p < n; ++p) {
            if (lab[p] < 0) throw std::invalid_argument("instance_groups: negative label");
            n_lab = std::max(n_lab, lab[p] + 1);
        }
        std::vector<int64_t> size(size_t(n_lab), 0), remap(size_t(n_lab), -1);
        for (size_t p = 0; p < n; ++p) ++size[lab[p]];
        int64_t g_n = 0;
        for (int64_t l = 0; l < n_lab; ++l)
            if (size[l] >= min_voxels) remap[l] = g_n++;
        const size_t G = size_t(g_n);
        counts.assign(G, 0);
        for (int64_t l = 0; l < n_lab; ++l)
            if (remap[l] >= 0) counts[remap[l]] = size[l];
        kept.reserve(n);
        klab.reserve(n);
        for (size_t p = 0; p < n; ++p)
            if (remap[lab[p]] >= 0) {
                kept.push_back(int64_t(p));
                klab.push_back(remap[lab[p]]);
            }
        const size_t M = kept.size();
        std::vector<int64_t> at(G, 0);
        for (size_t g = 1; g < G; ++g) at[g] = at[g - 1] + counts[g - 1];
        grouped.resize(M);
        for (size_t m = 0; m < M; ++m) grouped[at[klab[m]]++] = k[kept[m]];   // stable: key order in a group
        constexpr int64_t off = int64_t(1) << 20, mask = (int64_t(1) << 21) - 1;
        isum.assign(3 * G, 0);
        imin.assign(3 * G, std::numeric_limits<int64_t>::max());
        imax.assign(3 * G, std::numeric_limits<int64_t>::min());
        cmax.assign(G, -std::numeric_limits<double>::infinity());
        for (size_t m = 0; m < M; ++m) {
            const size_t g = size_t(klab[m]);
            const int64_t key = k[kept[m]];
            const int64_t ijk[3] = {(key >> 42) - off, ((key >> 21) & mask) - off, (key & mask) - off};
            for (int a = 0; a < 3; ++a) {
                isum[3 * g + a] += ijk[a];
                imin[3 * g + a] = std::min(imin[3 * g + a], ijk[a]);
                imax[3 * g + a] = std::max(imax[3 * g + a], ijk[a]);
            }
            cmax[g] = std::max(cmax[g], c[kept[m]]);
        }
    }
    const size_t M = kept.size(), G = counts.size();
    return nb::make_tuple(to_numpy(std::move(kept), {M}), to_numpy(std::move(klab), {M}),
                          to_numpy(std::move(grouped), {M}), to_numpy(std::move(counts), {G}),
                          to_numpy(std::move(isum), {G, 3}), to_numpy(std::move(imin), {G, 3}),
                          to_numpy(std::move(imax), {G, 3}), to_numpy(std::move(cmax), {G}));
}

// common.cones._weighted_union (file comment): local (m, 3), w (m,), frames (n, 3, 3) rows,
// o (n, 3) centred apexes, d (n, 3) unit axes; cones split over `threads` threads, each
// thread's sum added in cone order.
double cone_weighted_union(F64x3In local, F64In w, nb::ndarray<const double, nb::ndim<3>, nb::c_contig, nb::device::cpu> frames,
                           F64x3In o, F64x3In d, double range_m, double cos2, int threads) {
    const size_t m = local.shape(0), n = o.shape(0);
    if (w.shape(0) != m) throw std::invalid_argument("cone_weighted_union: w must be (m,)");
    if (d.shape(0) != n || frames.shape(0) != n || frames.shape(1) != 3 || frames.shape(2) != 3)
        throw std::invalid_argument("cone_weighted_union: frames (n, 3, 3), o and d (n, 3) must agree");
    std::vector<double> per_cone(n, 0.0);
    {
        nb::gil_scoped_release release;
        const double* L = local.data();
        const double* W = w.data();
        const double* F = frames.data();
        const double* O = o.data();
        const double* D = d.data();
        // the cones as columns (structure of arrays: the loop over cones vectorises)
        std::vector<double> dx(n), dy(n), dz(n), ox(n), oy(n), oz(n), od(n), oo(n);
        for (size_t j = 0; j < n; ++j) {
            dx[j] = D[3 * j], dy[j] = D[3 * j + 1], dz[j] = D[3 * j + 2];
            ox[j] = O[3 * j], oy[j] = O[3 * j + 1], oz[j] = O[3 * j + 2];
            od[j] = ox[j] * dx[j] + oy[j] * dy[j] + oz[j] * dz[j];
            oo[j] = ox[j] * ox[j] + oy[j] * oy[j] + oz[j] * oz[j];
        }
        auto in_cone = [&](double px, double py, double pz, double pp, size_t j) {
            const double t = px * dx[j] + py * dy[j] + pz * dz[j] - od[j];
            const double v2 = pp - 2.0 * (px * ox[j] + py * oy[j] + pz * oz[j]) + oo[j];
            return int((t > 0) & (t <= range_m) & (t * t >= v2 * cos2));
        };
        auto cones = [&](size_t i0, size_t i1) {
            for (size_t i = i0; i < i1; ++i) {
                const double* R = F + 9 * i;
                double sum = 0.0;
                for (size_t l = 0; l < m; ++l) {
                    const double* q = L + 3 * l;
                    double p[3];
                    for (int a = 0; a < 3; ++a) p[a] = q[0] * R[a] + q[1] * R[3 + a] + q[2] * R[6 + a] + O[3 * i + a];
                    const double px = p[0], py = p[1], pz = p[2];
                    const double pp = px * px + py * py + pz * pz;
                    int c = 1 - in_cone(px, py, pz, pp, i);       // its own cone, whatever the rounding
                    for (size_t j = 0; j < n; ++j) c += in_cone(px, py, pz, pp, j);
                    sum += W[l] / double(c);
                }
                per_cone[i] = sum;
            }
        };
        const size_t T = std::max<size_t>(1, std::min<size_t>({size_t(std::max(threads, 1)), n, m * n / 200000 + 1}));
        std::vector<std::thread> pool;
        for (size_t t = 1; t < T; ++t) pool.emplace_back(cones, t * n / T, (t + 1) * n / T);
        cones(0, n / T);
        for (auto& th : pool) th.join();
    }
    double total = 0.0;
    for (size_t i = 0; i < n; ++i) total += per_cone[i];
    return total;
}

// Stable argsort of packed voxel keys by LSD radix (file comment): (order, sorted keys), or
// None when the keys re-packed relative to their smallest index per axis need over 32 bits.
nb::object argsort_voxel_keys(I64In keys, int threads) {
    const size_t n = keys.shape(0);
    constexpr int64_t mask = (int64_t(1) << 21) - 1;
    std::vector<int64_t> order(n), sorted(n);
    bool fits = true;
    {
        nb::gil_scoped_release release;
        const int64_t* k = keys.data();
        int64_t lo[3] = {mask, mask, mask}, hi[3] = {0, 0, 0};
        for (size_t p = 0; p < n; ++p) {
            const int64_t f[3] = {(k[p] >> 42) & mask, (k[p] >> 21) & mask, k[p] & mask};
            for (int a = 0; a < 3; ++a) {
                lo[a] = std::min(lo[a], f[a]);
                hi[a] = std::max(hi[a], f[a]);
            }
            if ((k[p] >> 63) != 0) throw std::invalid_argument("argsort_voxel_keys: negative key");
        }
        int bits[3] = {0, 0, 0};
        for (int a = 0; a < 3 && n; ++a)
            while ((int64_t(1) << bits[a]) <= hi[a] - lo[a]) ++bits[a];
        const int total = bits[0] + bits[1] + bits[2];
        fits = total <= 32 && n < (size_t(1) << 32);
        if (fits && n) {
            // (compact key << 32 | position): the position rides along, so a key sort is stable
            std::vector<uint64_t> a(n), b(n);
            const size_t T = std::max<size_t>(1, std::min<size_t>(size_t(std::max(threads, 1)), n / 65536));
            auto parallel = [&](auto&& fn) {       // fn(lo, hi, t) over T contiguous parts
                std::vector<std::thread> pool;
                for (size_t t = 1; t < T; ++t) pool.emplace_back(fn, t * n / T, (t + 1) * n / T, t);
                fn(size_t(0), n / T, size_t(0));
                for (auto& th : pool) th.join();
            };
            parallel([&](size_t p0, size_t p1, size_t) {
                for (size_t p = p0; p < p1; ++p) {
                    const uint64_t c = (uint64_t(((k[p] >> 42) & mask) - lo[0]) << (bits[1] + bits[2])) |
                                       (uint64_t(((k[p] >> 21) & mask) - lo[1]) << bits[2]) |
                                       uint64_t((k[p] & mask) - lo[2]);
                    a[p] = (c << 32) | uint64_t(p);
                }
            });
            const int passes = (total + 10) / 11;
            const int digit = passes ? (total + passes - 1) / passes : 0;
            const size_t B = size_t(1) << digit;
            std::vector<std::vector<size_t>> hist(T, std::vector<size_t>(B));
            for (int pass = 0; pass < passes; ++pass) {
                const int shift = 32 + pass * digit;
                parallel([&](size_t p0, size_t p1, size_t t) {
                    std::fill(hist[t].begin(), hist[t].end(), size_t(0));
                    for (size_t p = p0; p < p1; ++p) ++hist[t][(a[p] >> shift) & (B - 1)];
                });
                size_t at = 0;                     // bucket-major, then part: stable
                for (size_t d = 0; d < B; ++d)
                    for (size_t t = 0; t < T; ++t) {
                        const size_t c = hist[t][d];
                        hist[t][d] = at;
                        at += c;
                    }
                parallel([&](size_t p0, size_t p1, size_t t) {
                    std::vector<size_t>& h = hist[t];
                    for (size_t p = p0; p < p1; ++p) b[h[(a[p] >> shift) & (B - 1)]++] = a[p];
                });
                a.swap(b);
            }
            parallel([&](size_t p0, size_t p1, size_t) {
                for (size_t p = p0; p < p1; ++p) {
                    const size_t i = size_t(a[p] & 0xffffffffu);
                    order[p] = int64_t(i);
                    sorted[p] = k[i];
                }
            });
        }
    }
    if (!fits) return nb::none();
    return nb::make_tuple(to_numpy(std::move(order), {n}), to_numpy(std::move(sorted), {n}));
}

}  // namespace

NB_MODULE(_rfkernels, m) {
    m.doc() = "CPU kernels for the RayFronts mapper (hash unique, ray-frontier candidates); see semantic_map.kernels";
    m.def("unique_i64", &unique_i64, nb::arg("keys"));
    m.def("components_26_sorted", &components_26_sorted, nb::arg("keys"), nb::arg("threads") = 1);
    m.def("cone_weighted_union", &cone_weighted_union, nb::arg("local"), nb::arg("w"), nb::arg("frames"), nb::arg("o"),
          nb::arg("d"), nb::arg("range_m"), nb::arg("cos2"), nb::arg("threads") = 1);
    m.def("argsort_voxel_keys", &argsort_voxel_keys, nb::arg("keys"), nb::arg("threads") = 1);
    m.def("instance_groups", &instance_groups, nb::arg("keys"), nb::arg("labels"), nb::arg("conf"),
          nb::arg("min_voxels"));
    m.def("group_pairs", &group_pairs, nb::arg("group"), nb::arg("idx"), nb::arg("wt"), nb::arg("n_groups"),
          nb::arg("n_src"));
    m.def("sample_pairs", &sample_pairs, nb::arg("group"), nb::arg("pix"), nb::arg("H"), nb::arg("W"), nb::arg("h"),
          nb::arg("w"), nb::arg("nearest"), nb::arg("n_groups"));
    m.def("voxel_keys_f64", &voxel_keys_f64, nb::arg("xyz"), nb::arg("vox"));
    m.def("voxel_keys_f32", &voxel_keys_f32, nb::arg("xyz"), nb::arg("vox"));
    m.def("surface_samples", &surface_samples, nb::arg("origin"), nb::arg("D"), nb::arg("depth"), nb::arg("pix"),
          nb::arg("offs"), nb::arg("vox"));
    m.def("segment_cells_unique", &segment_cells_unique, nb::arg("origins"), nb::arg("ends"), nb::arg("cell"),
          nb::arg("chunk_lo"), nb::arg("chunk_hi"), nb::arg("chunk_base"), nb::arg("exclude_end"),
          nb::arg("include_start"));
    register_ray_association(m);
    register_half_scores(m);
}
