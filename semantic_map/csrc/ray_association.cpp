// Ray -> frontier association (semantic_map/ray_frontiers.py; see rfkernels.cpp's header):
//
// * associate_rays(...): candidate pairs of rays against frontier cells (a block index of
//   the cells is built each call).
// * argmin_cost(...): the per-ray choice among the pairs.
//
// Rays are walked (3-D DDA) through a grid of blocks of `block`^3 coarse cells; a block lists
// the frontiers whose cell lies in the block grown by one cell, which holds every frontier
// within beta of any point of the block, so the walk has half a cell of slack and needs no
// exact grazing. Per pair the test is computed exactly as the torch code does (float32,
// relative to `base`, sums left to right, scalar thresholds rounded to float32); the two
// square roots per pair are left to torch (its float32 sqrt is not always correctly rounded,
// so only torch can reproduce torch).

#include "ray_association.h"

#include "arrays.h"
#include "key_ids.h"
#include "numpy_out.h"

#include <nanobind/ndarray.h>
#include <nanobind/stl/tuple.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <vector>

namespace nb = nanobind;
using namespace rfk::arrays;
using rfk::KeyIds;

namespace {

inline int64_t floordiv(int64_t a, int64_t b) {
    int64_t q = a / b;
    return (a % b != 0 && ((a < 0) != (b < 0))) ? q - 1 : q;
}

inline int64_t block_key(int64_t i, int64_t j, int64_t k) {
    constexpr int64_t off = int64_t(1) << 20, m = (int64_t(1) << 21) - 1;
    return (((i + off) & m) << 42) | (((j + off) & m) << 21) | ((k + off) & m);
}

// The blocks whose cells grown by one cell contain cell c: [lo, hi] per axis.
inline void blocks_of(const int64_t c[3], int64_t block, int64_t lo[3], int64_t hi[3]) {
    for (int a = 0; a < 3; ++a) {
        lo[a] = floordiv(c[a] - 1, block);
        hi[a] = floordiv(c[a] + 1, block);
    }
}

// One listed frontier: its centre in float32 relative to the call's base point, its row.
struct Entry {
    float p[3];
    int32_t f;
};

// The block lists of one call (CSR): frontier f is listed in every block whose cells grown by
// one cell contain f's cell. Blocks are found through a dense grid over the frontiers' block
// range when it is small enough (one array read per step of the walk), else by hashing.
class BlockLists {
public:
    BlockLists(const int64_t* c, size_t F, int64_t block, double beta, const double bs[3]) {
        for (int a = 0; a < 3; ++a) {
            lo_[a] = std::numeric_limits<int64_t>::max();
            hi_[a] = std::numeric_limits<int64_t>::min();
        }
        for (size_t f = 0; f < F; ++f) {
            int64_t blo[3], bhi[3];
            blocks_of(c + 3 * f, block, blo, bhi);
            for (int a = 0; a < 3; ++a) {
                lo_[a] = std::min(lo_[a], blo[a]);
                hi_[a] = std::max(hi_[a], bhi[a]);
            }
        }
        double cells = 1.0;
        for (int a = 0; a < 3; ++a) {
            n_[a] = F ? hi_[a] - lo_[a] + 1 : 0;
            cells *= double(n_[a]);
        }
        dense_ = F && cells <= double(kDenseBlocks);
        // (frontier, block id) pairs, up to 8 per frontier
        std::vector<int64_t> fb;
        fb.reserve(4 * F);
        size_t n_blocks = dense_ ? size_t(cells) : 0;
        for (size_t f = 0; f < F; ++f) {
            int64_t blo[3], bhi[3];
            blocks_of(c + 3 * f, block, blo, bhi);
            for (int64_t i = blo[0]; i <= bhi[0]; ++i)
                for (int64_t j = blo[1]; j <= bhi[1]; ++j)
                    for (int64_t k = blo[2]; k <= bhi[2]; ++k) {
                        fb.push_back(int64_t(f));
                        fb.push_back(dense_ ? cell_of(i, j, k) : hashed_.insert(block_key(i, j, k)));
                    }
        }
        if (!dense_) n_blocks = hashed_.keys().size();
        start_.assign(n_blocks + 1, 0);
        list_.resize(fb.size() / 2);
        for (size_t q = 1; q < fb.size(); q += 2) ++start_[size_t(fb[q]) + 1];
        for (size_t b = 0; b < n_blocks; ++b) start_[b + 1] += start_[b];
        std::vector<int32_t> fill(start_.begin(), start_.end() - 1);
        for (size_t q = 0; q < fb.size(); q += 2) {
            const int64_t f = fb[q];
            Entry& e = list_[size_t(fill[size_t(fb[q + 1])]++)];
            for (int a = 0; a < 3; ++a) e.p[a] = float((double(c[3 * f + a]) + 0.5) * beta - bs[a]);
            e.f = int32_t(f);
        }
    }
    // false once block (i, j, k) is past the listed range along an axis the walk moves away on
    bool ahead(const int64_t cur[3], const int64_t step[3]) const {
        for (int a = 0; a < 3; ++a)
            if ((step[a] > 0 && cur[a] > hi_[a]) || (step[a] < 0 && cur[a] < lo_[a])) return false;
        return true;
    }
    // the entries of block (i, j, k): [first, last)
    std::pair<const Entry*, const Entry*> at(int64_t i, int64_t j, int64_t k) const {
        if (i < lo_[0] || i > hi_[0] || j < lo_[1] || j > hi_[1] || k < lo_[2] || k > hi_[2]) return {nullptr, nullptr};
        const int64_t b = dense_ ? cell_of(i, j, k) : hashed_.find(block_key(i, j, k));
        if (b < 0) return {nullptr, nullptr};
        return {list_.data() + start_[size_t(b)], list_.data() + start_[size_t(b) + 1]};
    }

private:
    static constexpr int64_t kDenseBlocks = int64_t(1) << 22;  // 16 MiB of int32 starts at most
    int64_t cell_of(int64_t i, int64_t j, int64_t k) const {
        return ((i - lo_[0]) * n_[1] + (j - lo_[1])) * n_[2] + (k - lo_[2]);
    }
    int64_t lo_[3], hi_[3], n_[3];
    bool dense_ = false;
    KeyIds hashed_{16};
    std::vector<int32_t> start_;
    std::vector<Entry> list_;
};

// Candidate pairs of rays (o, d, length) against the frontier cells `fijk`: every ray is walked
// through the blocks of side beta * block (3-D DDA) and each frontier listed in a visited
// block is tested once per ray. Returns the passing pairs grouped by ray (ascending), each
// once: (ray, row of fijk, float32 d_ortho^2, float32 d_orig^2); argmin_cost then picks per ray.
nb::tuple associate_rays(F64x3In origins, F64x3In dirs, F64In lengths, I64x3In fijk, double beta,
                         int64_t block, F64In base, double max_dist, bool reject_close) {
    const size_t R = origins.shape(0), F = fijk.shape(0);
    if (dirs.shape(0) != R || lengths.shape(0) != R)
        throw std::invalid_argument("origins, dirs and lengths must have the same number of rows");
    if (!(beta > 0) || block < 1) throw std::invalid_argument("beta must be > 0 and block >= 1");
    if (base.shape(0) != 3) throw std::invalid_argument("base must have 3 values");
    if (F > size_t(std::numeric_limits<int32_t>::max()) || R > size_t(std::numeric_limits<int32_t>::max()))
        throw std::invalid_argument("too many rays or frontiers for one call");
    std::vector<int64_t> out_r, out_f;
    std::vector<float> out_oo, out_vv;
    {
        nb::gil_scoped_release release;
        const double* o = origins.data();
        const double* d = dirs.data();
        const double* L = lengths.data();
        const double bs[3] = {base.data()[0], base.data()[1], base.data()[2]};
        const BlockLists lists(fijk.data(), F, block, beta, bs);
        std::vector<int32_t> stamp(F, -1);
        const double h = beta * double(block);
        // thresholds as torch compares them: python double scalar -> float32
        const float beta2 = float(beta * beta);
        const float md2 = float(max_dist * max_dist);
        const float close2 = float(4.0 * beta * beta);
        for (size_t r = 0; r < R; ++r) {
            const double ov[3] = {o[3 * r], o[3 * r + 1], o[3 * r + 2]};
            const double dv[3] = {d[3 * r], d[3 * r + 1], d[3 * r + 2]};
            const double len = L[r];
            if (!std::isfinite(ov[0] + ov[1] + ov[2] + dv[0] + dv[1] + dv[2] + len)) continue;
            const float o32[3] = {float(ov[0] - bs[0]), float(ov[1] - bs[1]), float(ov[2] - bs[2])};
            const float d32[3] = {float(dv[0]), float(dv[1]), float(dv[2])};
            int64_t cur[3], remaining[3], step[3];
            double tmax[3], tdelta[3];
            for (int a = 0; a < 3; ++a) {
                cur[a] = int64_t(std::floor(ov[a] / h));
                int64_t e = int64_t(std::floor((ov[a] + dv[a] * len) / h));
                step[a] = e > cur[a] ? 1 : -1;
                remaining[a] = e > cur[a] ? e - cur[a] : cur[a] - e;
                if (remaining[a] > 0 && dv[a] != 0.0) {
                    double plane = double(cur[a] + (step[a] > 0 ? 1 : 0)) * h;
                    tmax[a] = (plane - ov[a]) / dv[a];
                    tdelta[a] = h / std::fabs(dv[a]);
                } else {
                    remaining[a] = 0;
                    step[a] = 0;  // no movement along a (the range test ignores it)
                    tmax[a] = std::numeric_limits<double>::infinity();
                    tdelta[a] = 0.0;
                }
            }
            const int32_t tag = int32_t(r);
            while (true) {
                const auto span = lists.at(cur[0], cur[1], cur[2]);
                for (const Entry* e = span.first; e != span.second; ++e) {
                    if (stamp[size_t(e->f)] == tag) continue;
                    stamp[size_t(e->f)] = tag;
                    const float vx = e->p[0] - o32[0], vy = e->p[1] - o32[1], vz = e->p[2] - o32[2];
                    const float px = vx * d32[0], py = vy * d32[1], pz = vz * d32[2];
                    const float t = (px + py) + pz;
                    const float sx = vx * vx, sy = vy * vy, sz = vz * vz;
                    const float vv = (sx + sy) + sz;
                    const float tt = t * t;
                    float oo = vv - tt;
                    if (oo < 0.0f) oo = 0.0f;
                    if (!(t > 0.0f && oo <= beta2)) continue;
                    if (max_dist > 0 && !(vv <= md2)) continue;
                    if (reject_close && !(vv >= close2)) continue;
                    out_r.push_back(int64_t(r));
                    out_f.push_back(e->f);
                    out_oo.push_back(oo);
                    out_vv.push_back(vv);
                }
                int a = 0;
                if (tmax[1] < tmax[a]) a = 1;
                if (tmax[2] < tmax[a]) a = 2;
                if (remaining[a] == 0) break;  // every axis done (its tmax is +inf)
                cur[a] += step[a];
                if (--remaining[a] == 0) tmax[a] = std::numeric_limits<double>::infinity();
                else tmax[a] += tdelta[a];
                if (!lists.ahead(cur, step)) break;  // a line never comes back into the box
            }
        }
    }
    size_t k = out_r.size();
    return nb::make_tuple(to_numpy(std::move(out_r), {k}), to_numpy(std::move(out_f), {k}),
                          to_numpy(std::move(out_oo), {k}), to_numpy(std::move(out_vv), {k}));
}

// Per-ray argmin of the normalised cost over candidate pairs grouped by ray (ray ids
// non-decreasing): cost = (x1 / max_ray x1 + x2 / max_ray x2) / 2 (a 0/0 term is 0), ties to
// the lowest frontier index; the same float64 operations as the torch code.
nb::tuple argmin_cost(I64In rays, I64In fidx, F64In x1, F64In x2) {
    const size_t K = rays.shape(0);
    if (fidx.shape(0) != K || x1.shape(0) != K || x2.shape(0) != K)
        throw std::invalid_argument("rays, fidx, x1 and x2 must have the same length");
    std::vector<int64_t> out_r, out_f;
    std::vector<double> out_c;
    {
        nb::gil_scoped_release release;
        const int64_t* ri = rays.data();
        const int64_t* fi = fidx.data();
        const double* a = x1.data();
        const double* b = x2.data();
        size_t s = 0;
        while (s < K) {
            size_t e = s;
            double m1 = 0.0, m2 = 0.0;
            while (e < K && ri[e] == ri[s]) {
                m1 = std::max(m1, a[e]);
                m2 = std::max(m2, b[e]);
                ++e;
            }
            if (e < K && ri[e] < ri[s]) throw std::invalid_argument("rays must be grouped in ascending order");
            double best = std::numeric_limits<double>::infinity();
            int64_t bf = std::numeric_limits<int64_t>::max();
            for (size_t q = s; q < e; ++q) {
                double cost = 0.0;
                cost += m1 > 0 ? a[q] / m1 : 0.0;
                cost += m2 > 0 ? b[q] / m2 : 0.0;
                cost /= 2.0;
                if (cost < best || (cost == best && fi[q] < bf)) {
                    best = cost;
                    bf = fi[q];
                }
            }
            if (std::isfinite(best)) {
                out_r.push_back(ri[s]);
                out_f.push_back(bf);
                out_c.push_back(best);
            }
            s = e;
        }
    }
    size_t k = out_r.size();
    return nb::make_tuple(to_numpy(std::move(out_r), {k}), to_numpy(std::move(out_f), {k}),
                          to_numpy(std::move(out_c), {k}));
}

}  // namespace

void register_ray_association(nb::module_& m) {
    m.def("associate_rays", &associate_rays, nb::arg("origins"), nb::arg("dirs"), nb::arg("lengths"),
          nb::arg("frontier_ijk"), nb::arg("beta"), nb::arg("block"), nb::arg("base"), nb::arg("max_dist"),
          nb::arg("reject_close"));
    m.def("argmin_cost", &argmin_cost, nb::arg("rays"), nb::arg("fidx"), nb::arg("x1"), nb::arg("x2"));
}
