// Ray -> frontier association (semantic_map/ray_frontiers.py; see rfkernels.cpp's header):
//
// * associate_rays(...): candidate pairs of rays against frontier cells (a block index of
//   the cells is built each call).
// * associate_rays_fan(...): the same pairs for rays that leave from a few points (a ray
//   block's cameras): per origin, the rays are binned by direction and each frontier tests
//   the rays of the bins its cone of candidate directions overlaps.
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

constexpr double kPi = 3.14159265358979323846;

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

// The exact per-pair test of the torch code (semantic_map.ray_frontiers._select): float32,
// relative to the base point, sums left to right, scalar thresholds rounded to float32 as
// torch compares a tensor with a python float.
struct PairTest {
    float beta2, md2, close2;
    bool limit, reject_close;
    PairTest(double beta, double max_dist, bool reject)
        : beta2(float(beta * beta)), md2(float(max_dist * max_dist)), close2(float(4.0 * beta * beta)),
          limit(max_dist > 0), reject_close(reject) {}
    // frontier centre p32 and ray (o32, d32): passes? then oo = d_ortho^2, vv = d_orig^2
    bool pass(const float p32[3], const float o32[3], const float d32[3], float& oo, float& vv) const {
        const float vx = p32[0] - o32[0], vy = p32[1] - o32[1], vz = p32[2] - o32[2];
        const float px = vx * d32[0], py = vy * d32[1], pz = vz * d32[2];
        const float t = (px + py) + pz;
        const float sx = vx * vx, sy = vy * vy, sz = vz * vz;
        vv = (sx + sy) + sz;
        const float tt = t * t;
        oo = vv - tt;
        if (oo < 0.0f) oo = 0.0f;
        if (!(t > 0.0f && oo <= beta2)) return false;
        if (limit && !(vv <= md2)) return false;
        if (reject_close && !(vv >= close2)) return false;
        return true;
    }
};

inline float centre32(int64_t c, double beta, double base) { return float((double(c) + 0.5) * beta - base); }

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
            for (int a = 0; a < 3; ++a) e.p[a] = centre32(c[3 * f + a], beta, bs[a]);
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
        const PairTest test(beta, max_dist, reject_close);
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
                    float oo, vv;
                    if (!test.pass(e->p, o32, d32, oo, vv)) continue;
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

// Ray directions from one origin binned on a latitude-longitude grid (CSR): latitude
// phi = asin(d_z) in rows of `cell` radians from -pi/2, longitude theta = atan2(d_y, d_x) in
// columns of ~`cell` radians from -pi (wrapping).
class DirectionBins {
public:
    DirectionBins(double cell) : dphi_(cell) {
        n_phi_ = std::max<int64_t>(1, int64_t(std::ceil(kPi / cell)));
        n_theta_ = std::max<int64_t>(1, int64_t(std::ceil(2.0 * kPi / cell)));
        dtheta_ = 2.0 * kPi / double(n_theta_);
        start_.assign(size_t(n_phi_ * n_theta_) + 1, 0);
    }
    void fill(const std::vector<int32_t>& rays, const double* d) {
        std::fill(start_.begin(), start_.end(), 0);
        bins_.resize(rays.size());
        for (size_t q = 0; q < rays.size(); ++q) {
            const double* v = d + 3 * size_t(rays[q]);
            const double n = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
            const int64_t i = row(std::asin(std::clamp(v[2] / n, -1.0, 1.0)));
            const int64_t j = col(std::atan2(v[1], v[0]));
            bins_[q] = i * n_theta_ + j;
            ++start_[size_t(bins_[q]) + 1];
        }
        for (size_t b = 1; b < start_.size(); ++b) start_[b] += start_[b - 1];
        row_lo_ = n_phi_;
        row_hi_ = -1;
        for (int64_t b : bins_) {
            row_lo_ = std::min(row_lo_, b / n_theta_);
            row_hi_ = std::max(row_hi_, b / n_theta_);
        }
        rays_.resize(rays.size());
        std::vector<int32_t> at(start_.begin(), start_.end() - 1);
        for (size_t q = 0; q < rays.size(); ++q) rays_[size_t(at[size_t(bins_[q])]++)] = rays[q];
    }
    // calls f(ray) for every ray whose bin overlaps the cap of angular radius alpha around
    // the unit direction u (a superset of the rays within alpha of u)
    template <class Fn>
    void cap(const double u[3], double alpha, Fn&& f) const {
        const double phi0 = std::asin(std::clamp(u[2], -1.0, 1.0));
        const double lo = phi0 - alpha, hi = phi0 + alpha;
        const int64_t i0 = std::max(row(lo), row_lo_), i1 = std::min(row(hi), row_hi_);
        if (i0 > i1) return;  // no ray at these latitudes
        int64_t j0 = 0, n_cols = n_theta_;
        if (lo > -kPi / 2 && hi < kPi / 2) {  // the cap holds no pole
            const double w = std::asin(std::min(1.0, std::sin(alpha) / std::cos(phi0))) + 1e-9;
            const double theta0 = std::atan2(u[1], u[0]);
            const int64_t a = int64_t(std::floor((theta0 - w + kPi) / dtheta_));
            const int64_t b = int64_t(std::floor((theta0 + w + kPi) / dtheta_));
            if (b - a + 1 < n_theta_) {
                j0 = ((a % n_theta_) + n_theta_) % n_theta_;
                n_cols = b - a + 1;
            }
        }
        // columns j0 .. j0 + n_cols - 1, wrapping: [j0, first_end) then [0, n_cols - (first_end - j0))
        const int64_t first_end = std::min(n_theta_, j0 + n_cols), wrapped = n_cols - (first_end - j0);
        for (int64_t i = i0; i <= i1; ++i) {
            const int32_t* st = start_.data() + i * n_theta_;
            for (int32_t q = st[j0]; q < st[first_end]; ++q) f(rays_[size_t(q)]);
            if (wrapped > 0)
                for (int32_t q = st[0]; q < st[wrapped]; ++q) f(rays_[size_t(q)]);
        }
    }
    template <class Fn>
    void all(Fn&& f) const {
        for (int32_t r : rays_) f(r);
    }

private:
    int64_t row(double phi) const {
        return std::clamp<int64_t>(int64_t(std::floor((phi + kPi / 2) / dphi_)), 0, n_phi_ - 1);
    }
    int64_t col(double theta) const {
        const int64_t j = int64_t(std::floor((theta + kPi) / dtheta_));
        return ((j % n_theta_) + n_theta_) % n_theta_;
    }
    double dphi_, dtheta_;
    int64_t n_phi_, n_theta_, row_lo_ = 0, row_hi_ = -1;
    std::vector<int32_t> start_, rays_;
    std::vector<int64_t> bins_;
};

// associate_rays' pairs (same order contract) for rays with max_dist > 0 leaving from a few
// points (a ray block's cameras); None when they do not (the caller walks instead). The rays
// are fanned out from a centre C: when every origin lies within `max_spread` of the origins'
// mean, C is that mean and s the largest origin's distance from it (one fan); else each
// distinct origin is its own fan (s = 0), at most `max_origins` of them. A frontier centre p
// passing with a ray from O (|O - C| <= s) lies within beta' + s of the parallel ray from C
// and within max_dist + s of C; so, with r = |p - C|, the ray points within
// asin((beta' + s) / r) of p - C, or r <= sqrt(s^2 + (beta' + s)^2) (then every ray is
// tested). beta'^2 = beta^2 + 1e-5 r^2 + 1e-4 covers the float32 test (the cancellation in
// vv - t^2, unit directions to 5e-6: the caller checks 1e-6); max_dist gets (1 + 1e-6) +
// 1e-3. Each candidate runs the exact float32 test (PairTest) with its own origin. A fan
// tests only frontiers whose cap meets the rays' latitude range.
nb::object associate_rays_fan(F64x3In origins, F64x3In dirs, I64x3In fijk, double beta, F64In base,
                              double max_dist, bool reject_close, double bin_rad, double max_spread,
                              int64_t max_origins) {
    const size_t R = origins.shape(0), F = fijk.shape(0);
    if (dirs.shape(0) != R) throw std::invalid_argument("origins and dirs must have the same number of rows");
    if (!(beta > 0) || !(max_dist > 0) || !(bin_rad > 0))
        throw std::invalid_argument("beta, max_dist and bin_rad must be > 0");
    if (base.shape(0) != 3) throw std::invalid_argument("base must have 3 values");
    if (F > size_t(std::numeric_limits<int32_t>::max()) || R > size_t(std::numeric_limits<int32_t>::max()))
        throw std::invalid_argument("too many rays or frontiers for one call");
    std::vector<int64_t> out_r, out_f;
    std::vector<float> out_oo, out_vv;
    bool refused = false;
    {
        nb::gil_scoped_release release;
        const double* o = origins.data();
        const double* d = dirs.data();
        const int64_t* c = fijk.data();
        const double bs[3] = {base.data()[0], base.data()[1], base.data()[2]};
        std::vector<int32_t> rays;  // finite rays (the walk skips the others too)
        rays.reserve(R);
        double mean[3] = {0.0, 0.0, 0.0};
        for (size_t r = 0; r < R; ++r)
            if (std::isfinite(o[3 * r] + o[3 * r + 1] + o[3 * r + 2] + d[3 * r] + d[3 * r + 1] + d[3 * r + 2])) {
                rays.push_back(int32_t(r));
                for (int a = 0; a < 3; ++a) mean[a] += o[3 * r + a];
            }
        // fans: (centre, spread, rays)
        struct Fan {
            double centre[3];
            double spread;
            std::vector<int32_t> rays;
        };
        std::vector<Fan> fans;
        if (!rays.empty()) {
            for (int a = 0; a < 3; ++a) mean[a] /= double(rays.size());
            double s2 = 0.0;
            for (int32_t r : rays) {
                double q = 0.0;
                for (int a = 0; a < 3; ++a) q += (o[3 * r + a] - mean[a]) * (o[3 * r + a] - mean[a]);
                s2 = std::max(s2, q);
            }
            if (std::sqrt(s2) <= max_spread) {
                fans.push_back({{mean[0], mean[1], mean[2]}, std::sqrt(s2) * (1.0 + 1e-9) + 1e-9, rays});
            } else {
                auto less = [o](int32_t a, int32_t b) {
                    for (int k = 0; k < 3; ++k)
                        if (o[3 * a + k] != o[3 * b + k]) return o[3 * a + k] < o[3 * b + k];
                    return a < b;
                };
                std::sort(rays.begin(), rays.end(), less);
                for (size_t s = 0; s < rays.size();) {
                    size_t e = s + 1;
                    const double* at = o + 3 * size_t(rays[s]);
                    while (e < rays.size() && o[3 * size_t(rays[e])] == at[0] && o[3 * size_t(rays[e]) + 1] == at[1]
                           && o[3 * size_t(rays[e]) + 2] == at[2])
                        ++e;
                    if (int64_t(fans.size()) == max_origins) {
                        refused = true;
                        break;
                    }
                    fans.push_back({{at[0], at[1], at[2]}, 0.0,
                                    std::vector<int32_t>(rays.begin() + long(s), rays.begin() + long(e))});
                    s = e;
                }
            }
        }
        if (!refused) {
            const PairTest test(beta, max_dist, reject_close);
            std::vector<float> p32(3 * F), o32(3 * R), d32(3 * R);
            for (size_t f = 0; f < F; ++f)
                for (int a = 0; a < 3; ++a) p32[3 * f + a] = centre32(c[3 * f + a], beta, bs[a]);
            for (int32_t r : rays)
                for (int a = 0; a < 3; ++a) {
                    o32[3 * size_t(r) + a] = float(o[3 * size_t(r) + a] - bs[a]);
                    d32[3 * size_t(r) + a] = float(d[3 * size_t(r) + a]);
                }
            DirectionBins bins(bin_rad);
            std::vector<int32_t> pr, pf;
            std::vector<float> poo, pvv;
            for (const Fan& fan : fans) {
                bins.fill(fan.rays, d);
                const double* C = fan.centre;
                const double sp = fan.spread;
                const double reach = max_dist * (1.0 + 1e-6) + 1e-3 + sp;
                for (size_t f = 0; f < F; ++f) {
                    double v[3];
                    for (int a = 0; a < 3; ++a) v[a] = (double(c[3 * f + a]) + 0.5) * beta - C[a];
                    const double r2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
                    if (r2 > reach * reach) continue;
                    const double b1 = std::sqrt(beta * beta + 1e-5 * (r2 + sp * sp + 2 * sp * std::sqrt(r2)) + 1e-4) + sp;
                    const float* pf32 = &p32[3 * f];
                    auto visit = [&](int32_t ray) {
                        float oo, vv;
                        if (!test.pass(pf32, &o32[3 * size_t(ray)], &d32[3 * size_t(ray)], oo, vv)) return;
                        pr.push_back(ray);
                        pf.push_back(int32_t(f));
                        poo.push_back(oo);
                        pvv.push_back(vv);
                    };
                    if (r2 <= sp * sp + b1 * b1) {
                        bins.all(visit);
                        continue;
                    }
                    const double r = std::sqrt(r2);
                    const double u[3] = {v[0] / r, v[1] / r, v[2] / r};
                    bins.cap(u, std::asin(std::min(1.0, b1 / r)) + 1e-9, visit);
                }
            }
            // group by ray, ascending (counting sort)
            std::vector<int64_t> at(R + 1, 0);
            for (int32_t r : pr) ++at[size_t(r) + 1];
            for (size_t r = 1; r <= R; ++r) at[r] += at[r - 1];
            const size_t K = pr.size();
            out_r.resize(K);
            out_f.resize(K);
            out_oo.resize(K);
            out_vv.resize(K);
            for (size_t q = 0; q < K; ++q) {
                const size_t w = size_t(at[size_t(pr[q])]++);
                out_r[w] = pr[q];
                out_f[w] = pf[q];
                out_oo[w] = poo[q];
                out_vv[w] = pvv[q];
            }
        }
    }
    if (refused) return nb::none();
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
    m.def("associate_rays_fan", &associate_rays_fan, nb::arg("origins"), nb::arg("dirs"), nb::arg("frontier_ijk"),
          nb::arg("beta"), nb::arg("base"), nb::arg("max_dist"), nb::arg("reject_close"), nb::arg("bin_rad"),
          nb::arg("max_spread"), nb::arg("max_origins"));
    m.def("argmin_cost", &argmin_cost, nb::arg("rays"), nb::arg("fidx"), nb::arg("x1"), nb::arg("x2"));
}
