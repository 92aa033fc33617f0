// semantic_map._vdbocc: an int8 log-odds occupancy grid stored in OpenVDB, for Python.
//
// The module owns an openvdb::Grid<Tree4<int8_t, 5, 4, 3>> with background 0 and exposes
// batched operations on voxel indices ijk = floor(xyz / vox) (int32, shape (N, 3)). Value
// semantics: > 0 occupied, < 0 free, 0 or inactive = unobserved. The Python wrapper
// (semantic_map/occupancy/vdb_backend.py) validates inputs; the torch backend
// (semantic_map/occupancy/torch_backend.py) implements the same operations bit for bit.
//
// Threading: writes are serial (VDB topology changes are not thread-safe); reads use TBB
// with one ConstAccessor per task. The GIL is released in every heavy call, and a
// shared_mutex per grid keeps concurrent Python threads from racing on the tree.

#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>

#include "numpy_out.h"

#include <openvdb/openvdb.h>
#include <openvdb/io/File.h>
#include <openvdb/tools/Prune.h>
#include <openvdb/tree/LeafManager.h>

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <mutex>
#include <shared_mutex>
#include <stdexcept>
#include <string>
#include <vector>

namespace nb = nanobind;

using TreeT = openvdb::tree::Tree4<int8_t, 5, 4, 3>::Type;
using GridT = openvdb::Grid<TreeT>;
using LeafT = TreeT::LeafNodeType;
using RootChildT = TreeT::RootNodeType::ChildNodeType;

// An active tile met in a bbox search: its bounds, the leaf-sized part of it to visit, its value.
struct TilePart {
    openvdb::CoordBBox tile, part;
    int8_t value;
};
using openvdb::Coord;
using openvdb::CoordBBox;

namespace {

// Index range shared with the torch backend (21-bit keys).
constexpr int64_t kIjkMin = -(int64_t(1) << 20);
constexpr int64_t kIjkMax = (int64_t(1) << 20) - 1;

using IjkIn = nb::ndarray<const int32_t, nb::shape<-1, 3>, nb::c_contig, nb::device::cpu>;
using I32In = nb::ndarray<const int32_t, nb::ndim<1>, nb::c_contig, nb::device::cpu>;
using I8In = nb::ndarray<const int8_t, nb::ndim<1>, nb::c_contig, nb::device::cpu>;
using F64x3In = nb::ndarray<const double, nb::shape<-1, 3>, nb::c_contig, nb::device::cpu>;


inline void classify(bool on, int8_t v, int& unobs, int& freec, int& occ) {
    if (!on || v == 0) ++unobs;
    else if (v < 0) ++freec;
    else ++occ;
}

class OccGrid {
public:
    OccGrid(double vox, int lo, int hi) : vox_(vox), lo_(lo), hi_(hi) {
        if (!(vox > 0.0) || !std::isfinite(vox))
            throw std::invalid_argument("voxel size must be a finite value > 0");
        if (lo < -128 || hi > 127 || lo > hi)
            throw std::invalid_argument("clamp bounds must satisfy -128 <= lo <= hi <= 127");
        grid_ = GridT::create(int8_t(0));
        init_grid();
    }

    explicit OccGrid(GridT::Ptr grid) : grid_(std::move(grid)) {
        vox_ = grid_->voxelSize()[0];
        auto lo = grid_->metaValue<int32_t>("occ_lo");
        auto hi = grid_->metaValue<int32_t>("occ_hi");
        lo_ = lo;
        hi_ = hi;
    }

    double vox() const { return vox_; }
    int lo() const { return lo_; }
    int hi() const { return hi_; }

    // value = clamp(value + inc, lo, hi), row by row (duplicates applied in order).
    void update(const IjkIn& ijk, const I32In& inc) {
        const int32_t* a = inc.data();
        write_rows(ijk, inc.shape(0), "inc", [&](auto& acc, const Coord& c, size_t i) {
            int8_t v = 0;
            const bool on = acc.probeValue(c, v);
            int64_t nv = int64_t(on ? v : 0) + int64_t(a[i]);
            nv = std::min<int64_t>(std::max<int64_t>(nv, lo_), hi_);
            acc.setValue(c, int8_t(nv));
        });
    }

    // Overwrite voxels with given values (snapshot restore); activates them.
    void set_values(const IjkIn& ijk, const I8In& vals) {
        const int8_t* v = vals.data();
        write_rows(ijk, vals.shape(0), "values", [&](auto& acc, const Coord& c, size_t i) { acc.setValue(c, v[i]); });
    }

    nb::ndarray<nb::numpy, int8_t> query(const IjkIn& ijk) const {
        const size_t n = ijk.shape(0);
        const int32_t* p = ijk.data();
        std::vector<int8_t> out(n, 0);
        {
            nb::gil_scoped_release release;
            std::shared_lock<std::shared_mutex> lock(mutex_);
            const TreeT& tree = grid_->constTree();
            tbb::parallel_for(tbb::blocked_range<size_t>(0, n, 16384),
                              [&](const tbb::blocked_range<size_t>& r) {
                openvdb::tree::ValueAccessor<const TreeT> acc(tree);
                for (size_t i = r.begin(); i < r.end(); ++i) {
                    int8_t v = 0;
                    const bool on = acc.probeValue(Coord(p[3 * i], p[3 * i + 1], p[3 * i + 2]), v);
                    out[i] = on ? v : 0;
                }
            });
        }
        return to_numpy(std::move(out), {n});
    }

    // Free voxels (value < 0) whose (2r+1)^3 neighbourhood, self included, holds at least
    // mu unobserved, mf free and mo occupied voxels; candidates limited to [bmin, bmax]
    // when use_bbox. Leaves and active tiles (pruned nodes) are both searched; within a
    // tile only the shell of thickness r can differ from the tile interior. Unsorted.
    nb::ndarray<nb::numpy, int32_t> frontiers(int mu, int mf, int mo, int r, bool use_bbox,
                                              std::tuple<int, int, int> bmin,
                                              std::tuple<int, int, int> bmax) const {
        if (r < 1 || r > 8) throw std::invalid_argument("radius must be in [1, 8]");
        CoordBBox cbox = CoordBBox::inf();
        if (use_bbox)
            cbox = CoordBBox(Coord(std::get<0>(bmin), std::get<1>(bmin), std::get<2>(bmin)),
                             Coord(std::get<0>(bmax), std::get<1>(bmax), std::get<2>(bmax)));
        std::vector<int32_t> result;
        if (use_bbox && cbox.empty()) return to_numpy(std::move(result), {size_t(0), size_t(3)});
        {
            nb::gil_scoped_release release;
            std::shared_lock<std::shared_mutex> lock(mutex_);
            const TreeT& tree = grid_->constTree();
            // Work: the leaves and active tiles to search, each tile with the part of it to
            // visit. A box is probed chunk by chunk when that is cheaper than iterating the
            // tree, and then read through a dense copy when the box is not much larger than
            // what the tree holds in it; otherwise the tree is iterated.
            std::vector<const LeafT*> leaves;
            std::vector<TilePart> tiles;
            bool dense = false;
            const CoordBBox ebox = use_bbox ? cbox.expandBy(r) : cbox;  // the box and the neighbours it reads
            if (use_bbox && probing_pays(tree, ebox)) {
                collect_in_bbox(tree, ebox, leaves, tiles);
                dense = dense_pays(ebox, leaves, tiles);
                if (dense) frontiers_dense(mu, mf, mo, r, cbox, leaves, tiles, result);
            } else {
                collect_all(tree, use_bbox ? &cbox : nullptr, leaves, tiles);
            }
            if (!dense) frontiers_sparse(tree, mu, mf, mo, r, use_bbox, cbox, leaves, tiles, result);
        }
        const size_t k = result.size() / 3;
        return to_numpy(std::move(result), {k, size_t(3)});
    }

    // frontiers() by testing each free voxel's (2r+1)^3 neighbourhood through an accessor, in
    // `leaves` and the free ones of `tiles` (candidates limited to cbox when use_bbox).
    static void frontiers_sparse(const TreeT& tree, int mu, int mf, int mo, int r, bool use_bbox,
                                 const CoordBBox& cbox, const std::vector<const LeafT*>& leaves,
                                 const std::vector<TilePart>& tiles, std::vector<int32_t>& out) {
        const int size = (2 * r + 1) * (2 * r + 1) * (2 * r + 1);
        tbb::enumerable_thread_specific<std::vector<int32_t>> found;

        auto test = [&](openvdb::tree::ValueAccessor<const TreeT>& acc, const Coord& c) {
            int unobs = 0, freec = 0, occ = 0;
            for (int dx = -r; dx <= r; ++dx)
                for (int dy = -r; dy <= r; ++dy)
                    for (int dz = -r; dz <= r; ++dz) {
                        int8_t v = 0;
                        const bool on = acc.probeValue(c.offsetBy(dx, dy, dz), v);
                        classify(on, v, unobs, freec, occ);
                    }
            return unobs >= mu && freec >= mf && occ >= mo;
        };
        auto emit = [](std::vector<int32_t>& out, const Coord& c) {
            out.push_back(c.x());
            out.push_back(c.y());
            out.push_back(c.z());
        };

        // 1) voxels in leaf nodes
        tbb::parallel_for(tbb::blocked_range<size_t>(0, leaves.size(), 64),
                          [&](const tbb::blocked_range<size_t>& range) {
            openvdb::tree::ValueAccessor<const TreeT> acc(tree);
            auto& out = found.local();
            for (size_t l = range.begin(); l < range.end(); ++l) {
                for (auto it = leaves[l]->cbeginValueOn(); it; ++it) {
                    if (*it >= 0) continue;
                    const Coord c = it.getCoord();
                    if (use_bbox && !cbox.isInside(c)) continue;
                    if (test(acc, c)) emit(out, c);
                }
            }
        });

        // 2) active tiles with a free value (pruned nodes).
        // A tile voxel farther than r from the tile's faces sees only the tile: all
        // `size` cells free, none unobserved or occupied.
        const bool interior_ok = (0 >= mu) && (size >= mf) && (0 >= mo);
        tbb::parallel_for(tbb::blocked_range<size_t>(0, tiles.size(), 1),
                          [&](const tbb::blocked_range<size_t>& range) {
            openvdb::tree::ValueAccessor<const TreeT> acc(tree);
            auto& out = found.local();
            for (size_t t = range.begin(); t < range.end(); ++t) {
                if (tiles[t].value >= 0) continue;  // only free tiles hold candidates
                const CoordBBox tb = tiles[t].tile;
                CoordBBox b = tiles[t].part;
                if (use_bbox) b.intersect(cbox);
                const Coord in_lo = tb.min().offsetBy(r), in_hi = tb.max().offsetBy(-r);
                auto shell = [&](int v, int axis) { return v < in_lo[axis] || v > in_hi[axis]; };
                for (int x = b.min().x(); x <= b.max().x(); ++x) {
                    const bool sx = shell(x, 0);
                    for (int y = b.min().y(); y <= b.max().y(); ++y) {
                        const bool sxy = sx || shell(y, 1);
                        if (sxy || interior_ok) {
                            for (int z = b.min().z(); z <= b.max().z(); ++z) {
                                const Coord c(x, y, z);
                                if (sxy || shell(z, 2)) {
                                    if (test(acc, c)) emit(out, c);
                                } else {
                                    emit(out, c);  // interior_ok
                                }
                            }
                        } else {
                            // only the two z-shell slabs can qualify
                            const int z0 = b.min().z(), z1 = b.max().z();
                            for (int z = z0; z <= std::min(z1, in_lo.z() - 1); ++z) {
                                const Coord c(x, y, z);
                                if (test(acc, c)) emit(out, c);
                            }
                            for (int z = std::max(z0, std::max(in_hi.z() + 1, in_lo.z())); z <= z1; ++z) {
                                const Coord c(x, y, z);
                                if (test(acc, c)) emit(out, c);
                            }
                        }
                    }
                }
            }
        });
        size_t total = out.size();
        for (auto& v : found) total += v.size();
        out.reserve(total);
        for (auto& v : found) out.insert(out.end(), v.begin(), v.end());
    }

    // Probing a box's leaf-sized chunks costs one lookup a chunk; iterating the tree one step a
    // leaf: probe unless the box has more chunks than the tree has leaves (and small boxes always).
    static bool probing_pays(const TreeT& tree, const CoordBBox& box) {
        constexpr double D = double(LeafT::DIM);
        const Coord dim = box.dim();
        const double chunks = (double(dim.x()) / D + 1) * (double(dim.y()) / D + 1) * (double(dim.z()) / D + 1);
        return chunks <= std::max(double(tree.leafCount()), 4096.0);
    }

    // A dense copy of `box` pays when the box is at most kDenseFrontierCells and at most
    // kDenseOverHeld times the cells the tree holds in it (`leaves` counted whole, `tiles`).
    static bool dense_pays(const CoordBBox& box, const std::vector<const LeafT*>& leaves,
                           const std::vector<TilePart>& tiles) {
        const double volume = double(box.volume());
        if (volume > double(kDenseFrontierCells)) return false;
        double held = double(leaves.size()) * double(LeafT::SIZE);
        for (const TilePart& t : tiles) {
            CoordBBox b = t.part;
            b.intersect(box);
            held += double(b.volume());
        }
        return volume <= kDenseOverHeld * held;
    }

    // Every leaf and active tile of the tree (those overlapping *box when given), by iterating it.
    static void collect_all(const TreeT& tree, const CoordBBox* box, std::vector<const LeafT*>& leaves,
                            std::vector<TilePart>& tiles) {
        for (auto it = tree.cbeginLeaf(); it; ++it)
            if (!box || box->hasOverlap(it->getNodeBoundingBox())) leaves.push_back(&*it);
        auto it = tree.cbeginValueOn();
        it.setMaxDepth(TreeT::ValueOnCIter::LEAF_DEPTH - 1);  // do not descend into leaves
        for (; it; ++it) {
            if (!it.isTileValue()) continue;
            CoordBBox b;
            it.getBoundingBox(b);
            if (!box || box->hasOverlap(b)) tiles.push_back({b, b, *it});
        }
    }

    // The leaves overlapping `box` and the active tiles overlapping it, each tile with
    // one leaf-sized chunk of it (so a tile spanning many chunks is listed once per chunk and
    // every voxel is visited once): found by probing the box's leaf-aligned chunks.
    static void collect_in_bbox(const TreeT& tree, const CoordBBox& box, std::vector<const LeafT*>& leaves,
                                std::vector<TilePart>& tiles) {
        // span of a tile by the depth getValueDepth reports (0: a root-table tile)
        static const int span[3] = {int(RootChildT::DIM), int(RootChildT::ChildNodeType::DIM), int(LeafT::DIM)};
        constexpr int D = int(LeafT::DIM);
        auto floor_to = [](int v, int m) { return v >= 0 ? (v / m) * m : -(((-v) + m - 1) / m) * m; };
        openvdb::tree::ValueAccessor<const TreeT> acc(tree);
        const Coord lo(floor_to(box.min().x(), D), floor_to(box.min().y(), D), floor_to(box.min().z(), D));
        for (int x = lo.x(); x <= box.max().x(); x += D)
            for (int y = lo.y(); y <= box.max().y(); y += D)
                for (int z = lo.z(); z <= box.max().z(); z += D) {
                    const Coord o(x, y, z);
                    if (const LeafT* leaf = acc.probeConstLeaf(o)) {
                        leaves.push_back(leaf);
                        continue;
                    }
                    const int depth = acc.getValueDepth(o);
                    int8_t v = 0;
                    if (depth < 0 || depth > 2 || !acc.probeValue(o, v)) continue;
                    const int sp = span[depth];
                    const Coord tmin(floor_to(x, sp), floor_to(y, sp), floor_to(z, sp));
                    tiles.push_back({CoordBBox(tmin, tmin.offsetBy(sp - 1)), CoordBBox(o, o.offsetBy(D - 1)), v});
                }
    }

    // Largest bbox (grown by the radius) searched through a dense copy, in cells (int8 state
    // + two uint16 count planes: 5 bytes a cell, 40 MiB at the cap), and how much larger than
    // the cells the tree holds in it the box may be: a box that is mostly unknown (two robots
    // far apart in one block) is searched sparsely.
    static constexpr int64_t kDenseFrontierCells = int64_t(1) << 23;
    static constexpr double kDenseOverHeld = 8.0;

    // frontiers() in a bbox through a dense copy of the box grown by r (`leaves` and `tiles`:
    // collect_in_bbox of that box): each cell's class
    // (unobserved / free / occupied, as classify), then the free and occupied counts of every
    // (2r+1)^3 window by three separable running sums; unobserved = size - free - occupied.
    // The cost follows the box's volume, not what the tree holds in it. Sorted (i, j, k).
    static void frontiers_dense(int mu, int mf, int mo, int r, const CoordBBox& cbox,
                                const std::vector<const LeafT*>& leaves, const std::vector<TilePart>& tiles,
                                std::vector<int32_t>& out) {
        const CoordBBox ebox = cbox.expandBy(r);
        const Coord e0 = ebox.min(), dim = ebox.dim();
        const int64_t nx = dim.x(), ny = dim.y(), nz = dim.z();
        const int64_t n = nx * ny * nz;
        auto at = [&](const Coord& c) { return ((int64_t(c.x() - e0.x()) * ny) + (c.y() - e0.y())) * nz + (c.z() - e0.z()); };
        // class per cell: 0 unobserved, 1 free, 2 occupied (inactive or 0 is unobserved)
        std::vector<uint8_t> cls(static_cast<size_t>(n), 0);
        for (const LeafT* leaf : leaves) {
            for (auto it = leaf->cbeginValueOn(); it; ++it) {
                const Coord c = it.getCoord();
                if (!ebox.isInside(c) || *it == 0) continue;
                cls[size_t(at(c))] = *it < 0 ? 1 : 2;
            }
        }
        for (const TilePart& tp : tiles) {
            CoordBBox b = tp.part;
            b.intersect(ebox);
            if (b.empty() || tp.value == 0) continue;
            const uint8_t v = tp.value < 0 ? 1 : 2;
            for (int x = b.min().x(); x <= b.max().x(); ++x)
                for (int y = b.min().y(); y <= b.max().y(); ++y) {
                    const int64_t row = at(Coord(x, y, b.min().z()));
                    std::fill(cls.begin() + row, cls.begin() + row + (b.max().z() - b.min().z() + 1), v);
                }
        }
        // window sums: free and occupied counts, z then y then x
        std::vector<uint16_t> fr(static_cast<size_t>(n)), oc(static_cast<size_t>(n));
        for (int64_t q = 0; q < n; ++q) {
            fr[size_t(q)] = cls[size_t(q)] == 1;
            oc[size_t(q)] = cls[size_t(q)] == 2;
        }
        box_sum(fr, nx, ny, nz, r);
        box_sum(oc, nx, ny, nz, r);
        const int size = (2 * r + 1) * (2 * r + 1) * (2 * r + 1);
        for (int x = cbox.min().x(); x <= cbox.max().x(); ++x)
            for (int y = cbox.min().y(); y <= cbox.max().y(); ++y) {
                const int64_t row = at(Coord(x, y, cbox.min().z()));
                for (int z = cbox.min().z(); z <= cbox.max().z(); ++z) {
                    const size_t q = size_t(row + (z - cbox.min().z()));
                    if (cls[q] != 1) continue;
                    const int f = fr[q], o = oc[q], u = size - f - o;
                    if (u >= mu && f >= mf && o >= mo) {
                        out.push_back(x);
                        out.push_back(y);
                        out.push_back(z);
                    }
                }
            }
    }

    // In place: a[x, y, z] = sum of a over the (2r+1)^3 window around (x, y, z) clipped to
    // the array (cells outside the array count 0: the caller's array is the box grown by r).
    static void box_sum(std::vector<uint16_t>& a, int64_t nx, int64_t ny, int64_t nz, int r) {
        std::vector<uint16_t> line(size_t(std::max(nx, std::max(ny, nz))));
        auto pass = [&](int64_t len, int64_t stride, int64_t count, auto base_of) {
            for (int64_t l = 0; l < count; ++l) {
                const int64_t b = base_of(l);
                for (int64_t i = 0; i < len; ++i) line[size_t(i)] = a[size_t(b + i * stride)];
                uint32_t s = 0;
                for (int64_t i = 0; i < std::min<int64_t>(r, len); ++i) s += line[size_t(i)];
                for (int64_t i = 0; i < len; ++i) {
                    if (i + r < len) s += line[size_t(i + r)];
                    a[size_t(b + i * stride)] = uint16_t(s);
                    if (i - r >= 0) s -= line[size_t(i - r)];
                }
            }
        };
        pass(nz, 1, nx * ny, [&](int64_t l) { return l * nz; });
        pass(ny, nz, nx * nz, [&](int64_t l) { return (l / nz) * ny * nz + (l % nz); });
        pass(nx, ny * nz, ny * nz, [&](int64_t l) { return l; });
    }

    void prune(int tol) {
        if (tol < 0 || tol > 127) throw std::invalid_argument("prune tolerance must be in [0, 127]");
        nb::gil_scoped_release release;
        std::unique_lock<std::shared_mutex> lock(mutex_);
        openvdb::tools::prune(grid_->tree(), int8_t(tol));
    }

    // All active voxels, tiles expanded: ((M, 3) int32, (M,) int8), unsorted.
    std::tuple<nb::ndarray<nb::numpy, int32_t>, nb::ndarray<nb::numpy, int8_t>> active() const {
        std::vector<int32_t> ijk;
        std::vector<int8_t> vals;
        {
            nb::gil_scoped_release release;
            std::shared_lock<std::shared_mutex> lock(mutex_);
            const TreeT& tree = grid_->constTree();
            const size_t m = size_t(tree.activeVoxelCount());
            ijk.resize(3 * m);
            vals.resize(m);
            // leaves in parallel at precomputed offsets, then tiles
            openvdb::tree::LeafManager<const TreeT> leaves(tree);
            const size_t nl = leaves.leafCount();
            std::vector<size_t> offs(nl + 1, 0);
            for (size_t i = 0; i < nl; ++i) offs[i + 1] = offs[i] + leaves.leaf(i).onVoxelCount();
            tbb::parallel_for(tbb::blocked_range<size_t>(0, nl, 64), [&](const tbb::blocked_range<size_t>& r) {
                for (size_t i = r.begin(); i < r.end(); ++i) {
                    size_t o = offs[i];
                    for (auto it = leaves.leaf(i).cbeginValueOn(); it; ++it, ++o) {
                        const Coord c = it.getCoord();
                        ijk[3 * o] = c.x();
                        ijk[3 * o + 1] = c.y();
                        ijk[3 * o + 2] = c.z();
                        vals[o] = *it;
                    }
                }
            });
            size_t o = offs[nl];
            auto it = tree.cbeginValueOn();
            it.setMaxDepth(TreeT::ValueOnCIter::LEAF_DEPTH - 1);
            for (; it; ++it) {
                if (!it.isTileValue()) continue;
                CoordBBox b;
                it.getBoundingBox(b);
                const int8_t v = *it;
                for (auto c = b.begin(); c; ++c, ++o) {
                    ijk[3 * o] = (*c).x();
                    ijk[3 * o + 1] = (*c).y();
                    ijk[3 * o + 2] = (*c).z();
                    vals[o] = v;
                }
            }
            if (o != m) throw std::runtime_error("active voxel count mismatch while expanding tiles");
        }
        const size_t m = vals.size();
        return {to_numpy(std::move(ijk), {m, size_t(3)}), to_numpy(std::move(vals), {m})};
    }

    // Amanatides–Woo traversal from the origin voxel v0 (= floor(o / vox), given); returns
    // max(0, entry distance) of the first voxel with value >= 0, +inf if none within
    // max_dist. Same arithmetic as the torch backend (float64, boundary distance
    // (nb * vox - o) / d recomputed per step, ties step the lowest axis).
    nb::ndarray<nb::numpy, double> first_blocked(const F64x3In& origins, const F64x3In& dirs,
                                                 const IjkIn& v0, double max_dist) const {
        const size_t n = origins.shape(0);
        if (dirs.shape(0) != n || v0.shape(0) != n)
            throw std::invalid_argument("origins, directions and origin voxels must have the same length");
        const double* po = origins.data();
        const double* pd = dirs.data();
        const int32_t* pv = v0.data();
        const double vox = vox_;
        std::vector<double> out(n, std::numeric_limits<double>::infinity());
        {
            nb::gil_scoped_release release;
            std::shared_lock<std::shared_mutex> lock(mutex_);
            const TreeT& tree = grid_->constTree();
            tbb::parallel_for(tbb::blocked_range<size_t>(0, n, 256), [&](const tbb::blocked_range<size_t>& r) {
                openvdb::tree::ValueAccessor<const TreeT> acc(tree);
                for (size_t i = r.begin(); i < r.end(); ++i) {
                    const double* o = po + 3 * i;
                    const double* d = pd + 3 * i;
                    int64_t v[3], nb_[3], step[3];
                    double tmax[3];
                    for (int a = 0; a < 3; ++a) {
                        v[a] = pv[3 * i + a];
                        step[a] = d[a] > 0 ? 1 : (d[a] < 0 ? -1 : 0);
                        nb_[a] = v[a] + (step[a] > 0 ? 1 : 0);
                        tmax[a] = d[a] != 0 ? (double(nb_[a]) * vox - o[a]) / d[a]
                                            : std::numeric_limits<double>::infinity();
                    }
                    double tent = 0.0;
                    for (;;) {
                        bool blocked = true;
                        if (v[0] >= kIjkMin && v[0] <= kIjkMax && v[1] >= kIjkMin && v[1] <= kIjkMax &&
                            v[2] >= kIjkMin && v[2] <= kIjkMax) {
                            int8_t val = 0;
                            const bool on = acc.probeValue(Coord(int32_t(v[0]), int32_t(v[1]), int32_t(v[2])), val);
                            blocked = !on || val >= 0;
                        }
                        if (blocked) {
                            out[i] = std::max(tent, 0.0);
                            break;
                        }
                        int a = 0;
                        if (tmax[1] < tmax[a]) a = 1;
                        if (tmax[2] < tmax[a]) a = 2;
                        const double t = tmax[a];
                        if (!(t <= max_dist)) break;  // stays +inf
                        v[a] += step[a];
                        nb_[a] += step[a];
                        tmax[a] = (double(nb_[a]) * vox - o[a]) / d[a];
                        tent = t;
                    }
                }
            });
        }
        return to_numpy(std::move(out), {n});
    }

    uint64_t num_active() const { return read_tree([](const TreeT& t) { return t.activeVoxelCount(); }); }
    uint64_t leaf_count() const { return read_tree([](const TreeT& t) { return t.leafCount(); }); }
    uint64_t tile_count() const { return read_tree([](const TreeT& t) { return t.activeTileCount(); }); }
    uint64_t mem_bytes() const { return read_tree([](const TreeT& t) { return t.memUsage(); }); }

    void save(const std::string& path) const {
        nb::gil_scoped_release release;
        std::shared_lock<std::shared_mutex> lock(mutex_);
        try {
            openvdb::io::File file(path);
            openvdb::GridPtrVec grids{grid_};
            file.write(grids);
            file.close();
        } catch (const openvdb::Exception& e) {
            throw std::runtime_error("cannot write " + path + ": " + e.what());
        }
    }

    static OccGrid* load(const std::string& path) {
        GridT::Ptr grid;
        {
            nb::gil_scoped_release release;
            try {
                openvdb::io::File file(path);
                file.open(false);  // read everything now (no delayed loading)
                openvdb::GridBase::Ptr base = file.readGrid("occupancy");
                file.close();
                grid = openvdb::gridPtrCast<GridT>(base);
            } catch (const openvdb::Exception& e) {
                throw std::invalid_argument("cannot read occupancy grid from " + path + ": " + e.what());
            }
        }
        if (!grid) throw std::invalid_argument(path + ": grid 'occupancy' is not an int8 Tree4<5,4,3> grid");
        if (!grid->getMetadata<openvdb::Int32Metadata>("occ_lo") || !grid->getMetadata<openvdb::Int32Metadata>("occ_hi"))
            throw std::invalid_argument(path + ": grid lacks the occ_lo/occ_hi metadata");
        return new OccGrid(grid);
    }

private:
    // Under the write lock with the GIL released: f(accessor, coord, i) for each row i of ijk
    // (rows applied in order); `what` (n values, one per row) names the value array in the error.
    template <typename F>
    void write_rows(const IjkIn& ijk, size_t n, const char* what, F&& f) {
        if (ijk.shape(0) != n) throw std::invalid_argument(std::string(what) + " must have one entry per row of ijk");
        const int32_t* p = ijk.data();
        nb::gil_scoped_release release;
        std::unique_lock<std::shared_mutex> lock(mutex_);
        auto acc = grid_->getAccessor();
        for (size_t i = 0; i < n; ++i) f(acc, Coord(p[3 * i], p[3 * i + 1], p[3 * i + 2]), i);
    }

    // f(tree) under the read lock (the GIL held: for quick counts).
    template <typename F>
    uint64_t read_tree(F&& f) const {
        std::shared_lock<std::shared_mutex> lock(mutex_);
        return uint64_t(f(grid_->constTree()));
    }

    void init_grid() {
        grid_->setTransform(openvdb::math::Transform::createLinearTransform(vox_));
        grid_->setName("occupancy");
        grid_->setGridClass(openvdb::GRID_UNKNOWN);
        grid_->insertMeta("occ_lo", openvdb::Int32Metadata(lo_));
        grid_->insertMeta("occ_hi", openvdb::Int32Metadata(hi_));
    }

    GridT::Ptr grid_;
    double vox_;
    int lo_, hi_;
    mutable std::shared_mutex mutex_;
};

// Write observed voxels as OpenVDB's standard grid types, readable by OpenVDB's own tools and
// its Python module (which know only the standard types, not this module's int8 tree):
//   FloatGrid "log_odds": the int8 log-odds as float (> 0 occupied, < 0 free), active where
//                         observed (value != 0); background 0, inactive = unknown;
//   BoolGrid  "occupied": true and active where the log-odds is > 0.
// Transform: linear, voxel size vox, translated by vox/2 so that index (i, j, k) lands on
// the centre of the map voxel covering [ijk*vox, (ijk+1)*vox) (metres, map frame). Each grid
// carries the int32 metadata occ_lo / occ_hi (clamp bounds), voxel_size_m and convention.
void write_standard(const std::string& path, const IjkIn& ijk, const I8In& vals, double vox, int lo, int hi,
                    const std::string& convention) {
    if (!(vox > 0.0) || !std::isfinite(vox)) throw std::invalid_argument("voxel size must be a finite value > 0");
    const size_t n = ijk.shape(0);
    if (vals.shape(0) != n) throw std::invalid_argument("values must have one entry per row of ijk");
    const int32_t* p = ijk.data();
    const int8_t* v = vals.data();
    nb::gil_scoped_release release;
    auto xform = openvdb::math::Transform::createLinearTransform(vox);
    xform->postTranslate(openvdb::Vec3d(0.5 * vox, 0.5 * vox, 0.5 * vox));
    auto logodds = openvdb::FloatGrid::create(0.0f);
    auto occupied = openvdb::BoolGrid::create(false);
    {
        auto la = logodds->getAccessor();
        auto oa = occupied->getAccessor();
        for (size_t i = 0; i < n; ++i) {
            if (v[i] == 0) continue;
            const Coord c(p[3 * i], p[3 * i + 1], p[3 * i + 2]);
            la.setValue(c, float(v[i]));
            if (v[i] > 0) oa.setValue(c, true);
        }
    }
    openvdb::GridPtrVec grids;
    for (openvdb::GridBase::Ptr g : {openvdb::GridBase::Ptr(logodds), openvdb::GridBase::Ptr(occupied)}) {
        g->setTransform(xform->copy());
        g->setGridClass(openvdb::GRID_UNKNOWN);
        g->insertMeta("occ_lo", openvdb::Int32Metadata(lo));
        g->insertMeta("occ_hi", openvdb::Int32Metadata(hi));
        g->insertMeta("voxel_size_m", openvdb::DoubleMetadata(vox));
        g->insertMeta("convention", openvdb::StringMetadata(convention));
        grids.push_back(g);
    }
    logodds->setName("log_odds");
    occupied->setName("occupied");
    try {
        openvdb::io::File file(path);
        file.write(grids);
        file.close();
    } catch (const openvdb::Exception& e) {
        throw std::runtime_error("cannot write " + path + ": " + e.what());
    }
}

}  // namespace

NB_MODULE(_vdbocc, m) {
    m.doc() = "int8 log-odds occupancy grid on OpenVDB (Tree4<int8_t,5,4,3>); see semantic_map.occupancy";
    openvdb::initialize();
    if (!GridT::isRegistered()) GridT::registerGrid();
    m.attr("OPENVDB_VERSION") = OPENVDB_LIBRARY_VERSION_STRING;

    nb::class_<OccGrid>(m, "Grid")
        .def(nb::init<double, int, int>(), nb::arg("vox"), nb::arg("lo"), nb::arg("hi"))
        .def_prop_ro("vox", &OccGrid::vox)
        .def_prop_ro("lo", &OccGrid::lo)
        .def_prop_ro("hi", &OccGrid::hi)
        .def("update", &OccGrid::update, nb::arg("ijk"), nb::arg("inc"))
        .def("set_values", &OccGrid::set_values, nb::arg("ijk"), nb::arg("values"))
        .def("query", &OccGrid::query, nb::arg("ijk"))
        .def("frontiers", &OccGrid::frontiers, nb::arg("min_unobserved"), nb::arg("min_free"),
             nb::arg("min_occupied"), nb::arg("radius"), nb::arg("use_bbox"), nb::arg("bmin"),
             nb::arg("bmax"))
        .def("prune", &OccGrid::prune, nb::arg("tolerance"))
        .def("active", &OccGrid::active)
        .def("first_blocked", &OccGrid::first_blocked, nb::arg("origins"), nb::arg("directions"),
             nb::arg("origin_voxels"), nb::arg("max_dist"))
        .def_prop_ro("num_active", &OccGrid::num_active)
        .def_prop_ro("leaf_count", &OccGrid::leaf_count)
        .def_prop_ro("tile_count", &OccGrid::tile_count)
        .def("mem_bytes", &OccGrid::mem_bytes)
        .def("save", &OccGrid::save, nb::arg("path"))
        .def_static("load", &OccGrid::load, nb::arg("path"), nb::rv_policy::take_ownership);
    m.def("write_standard", &write_standard, nb::arg("path"), nb::arg("ijk"), nb::arg("values"), nb::arg("vox"),
          nb::arg("lo"), nb::arg("hi"), nb::arg("convention"),
          "write observed voxels as a FloatGrid 'log_odds' and a BoolGrid 'occupied' (.vdb)");
}
