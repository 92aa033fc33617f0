// half_scores: the text-query product over the query snapshot's float16 copy
// (semantic_map.query_snapshot.HalfFeatures), fused with its per-row scale and mean term:
//
//     out[i] = (sum_d h[i, d] * q[d]) * a[i] + qm * b[i]        (float32)
//
// h: (N, D) float16 rows (passed as their int16 bits), q: (D,) float32, a, b: (N,) float32
// (b may be empty: no mean term). The products and the sum are float32, in the same order
// for every row wherever it lies (whole map or a subset, any thread split), so a row scores
// the same in both. torch's float16 matrix-vector product on a CPU without float16
// arithmetic runs well below memory bandwidth (AMD EPYC, 10 M x 100: ~175 ms for 2 GB that
// the memory delivers in ~70 ms); this kernel converts 8 halves per instruction (F16C) and
// walks 4 rows at once with two accumulators each (eight independent multiply-add chains),
// summing the four rows' lanes together, on `threads` threads (std::thread, GIL released).
//
// Only on x86-64 CPUs with AVX2, FMA and F16C (checked at run time: half_scores_available);
// elsewhere the Python side keeps torch's path.

#include "half_scores.h"

#include <nanobind/ndarray.h>

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <stdexcept>
#include <thread>
#include <vector>

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define RF_HALF_SCORES_X86 1
#endif

namespace nb = nanobind;

namespace {

using HalfRows = nb::ndarray<const int16_t, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
using F32In = nb::ndarray<const float, nb::ndim<1>, nb::c_contig, nb::device::cpu>;
using F32Out = nb::ndarray<float, nb::ndim<1>, nb::c_contig, nb::device::cpu>;

bool cpu_has_simd() {
#ifdef RF_HALF_SCORES_X86
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma") && __builtin_cpu_supports("f16c");
#else
    return false;
#endif
}

#ifdef RF_HALF_SCORES_X86
// Each row's sum in one fixed order, wherever the row lies (4 rows at once or alone): the
// 8-wide blocks alternate between two accumulators (even, odd blocks), added lane-wise; the
// first 4 products of the D % 8 tail go into lanes 0-3; the lanes are summed pairwise
// ((0+1)+(2+3)) + ((4+5)+(6+7)); the last D % 4 products follow in order; then the scale
// and the mean term as one fused multiply-add, s * a + qm * b.
__attribute__((target("avx2,fma,f16c"))) inline __m256 load8(const int16_t* p) {
    return _mm256_cvtph_ps(_mm_loadu_si128(reinterpret_cast<const __m128i*>(p)));
}

// One row's 8-lane accumulator: its blocks, then the tail's first 4 products in lanes 0-3.
__attribute__((target("avx2,fma,f16c"))) inline __m256 row_lanes(const int16_t* r, const float* q, size_t D8,
                                                                  size_t D, __m256 even, __m256 odd) {
    __m256 acc = _mm256_add_ps(even, odd);
    if (D - D8 >= 4) {
        const __m128 t = _mm_cvtph_ps(_mm_loadl_epi64(reinterpret_cast<const __m128i*>(r + D8)));
        const __m128 lo = _mm_fmadd_ps(t, _mm_loadu_ps(q + D8), _mm256_castps256_ps128(acc));
        acc = _mm256_insertf128_ps(acc, lo, 0);
    }
    return acc;
}

// The lane sums of four accumulators, [s0, s1, s2, s3], each ((0+1)+(2+3)) + ((4+5)+(6+7)).
__attribute__((target("avx2,fma,f16c"))) inline __m128 lane_sums(__m256 c0, __m256 c1, __m256 c2, __m256 c3) {
    const __m256 h = _mm256_hadd_ps(_mm256_hadd_ps(c0, c1), _mm256_hadd_ps(c2, c3));
    return _mm_add_ps(_mm256_castps256_ps128(h), _mm256_extractf128_ps(h, 1));
}

// Rows [i, i + m) (m <= 4) finished from their lane sums s: the D % 4 last products, the terms.
__attribute__((target("avx2,fma,f16c"))) inline void finish_rows(const int16_t* h, size_t D, size_t D4,
                                                                  const float* q, const float* a, const float* b,
                                                                  float qm, float* out, size_t i, size_t m,
                                                                  __m128 s) {
    alignas(16) float v[4], av[4] = {0, 0, 0, 0}, bv[4] = {0, 0, 0, 0};
    _mm_store_ps(v, s);
    for (size_t r = 0; r < m; ++r) {
        const int16_t* row = h + (i + r) * D;
        for (size_t d = D4; d < D; ++d) v[r] += _cvtsh_ss(static_cast<unsigned short>(row[d])) * q[d];
        av[r] = a[i + r];
        if (b) bv[r] = b[i + r];
    }
    __m128 o = _mm_mul_ps(_mm_load_ps(v), _mm_load_ps(av));
    if (b) o = _mm_fmadd_ps(_mm_set1_ps(qm), _mm_load_ps(bv), o);
    _mm_store_ps(v, o);
    for (size_t r = 0; r < m; ++r) out[i + r] = v[r];
}

// Rows [lo, hi): 4 rows at once (8 accumulators), the remainder one by one, the same sums.
__attribute__((target("avx2,fma,f16c"))) void score_rows(const int16_t* h, size_t D, const float* q,
                                                          const float* a, const float* b, float qm, float* out,
                                                          size_t lo, size_t hi) {
    const size_t D8 = D - D % 8, D4 = D - D % 4;
    const size_t blocks = D8 / 8;
    size_t i = lo;
    for (; i + 4 <= hi; i += 4) {
        const int16_t* r0 = h + i * D;
        const __m256 z = _mm256_setzero_ps();
        __m256 e0 = z, e1 = z, e2 = z, e3 = z, o0 = z, o1 = z, o2 = z, o3 = z;
        size_t blk = 0;
        for (; blk + 2 <= blocks; blk += 2) {
            const size_t d = blk * 8;
            const __m256 qe = _mm256_loadu_ps(q + d), qo = _mm256_loadu_ps(q + d + 8);
            e0 = _mm256_fmadd_ps(load8(r0 + d), qe, e0);
            e1 = _mm256_fmadd_ps(load8(r0 + D + d), qe, e1);
            e2 = _mm256_fmadd_ps(load8(r0 + 2 * D + d), qe, e2);
            e3 = _mm256_fmadd_ps(load8(r0 + 3 * D + d), qe, e3);
            o0 = _mm256_fmadd_ps(load8(r0 + d + 8), qo, o0);
            o1 = _mm256_fmadd_ps(load8(r0 + D + d + 8), qo, o1);
            o2 = _mm256_fmadd_ps(load8(r0 + 2 * D + d + 8), qo, o2);
            o3 = _mm256_fmadd_ps(load8(r0 + 3 * D + d + 8), qo, o3);
        }
        if (blk < blocks) {
            const size_t d = blk * 8;
            const __m256 qe = _mm256_loadu_ps(q + d);
            e0 = _mm256_fmadd_ps(load8(r0 + d), qe, e0);
            e1 = _mm256_fmadd_ps(load8(r0 + D + d), qe, e1);
            e2 = _mm256_fmadd_ps(load8(r0 + 2 * D + d), qe, e2);
            e3 = _mm256_fmadd_ps(load8(r0 + 3 * D + d), qe, e3);
        }
        const __m128 s = lane_sums(row_lanes(r0, q, D8, D, e0, o0), row_lanes(r0 + D, q, D8, D, e1, o1),
                                   row_lanes(r0 + 2 * D, q, D8, D, e2, o2), row_lanes(r0 + 3 * D, q, D8, D, e3, o3));
        finish_rows(h, D, D4, q, a, b, qm, out, i, 4, s);
    }
    for (; i < hi; ++i) {
        const int16_t* r = h + i * D;
        __m256 e = _mm256_setzero_ps(), o = e;
        size_t blk = 0;
        for (; blk + 2 <= blocks; blk += 2) {
            e = _mm256_fmadd_ps(load8(r + blk * 8), _mm256_loadu_ps(q + blk * 8), e);
            o = _mm256_fmadd_ps(load8(r + blk * 8 + 8), _mm256_loadu_ps(q + blk * 8 + 8), o);
        }
        if (blk < blocks) e = _mm256_fmadd_ps(load8(r + blk * 8), _mm256_loadu_ps(q + blk * 8), e);
        const __m256 c = row_lanes(r, q, D8, D, e, o);
        finish_rows(h, D, D4, q, a, b, qm, out, i, 1, lane_sums(c, c, c, c));
    }
}
#endif

void half_scores(HalfRows h, F32In q, F32In a, F32In b, float qm, F32Out out, int threads) {
    const size_t N = h.shape(0), D = h.shape(1);
    if (q.shape(0) != D) throw std::invalid_argument("half_scores: q must be (D,) for (N, D) rows");
    if (a.shape(0) != N || out.shape(0) != N) throw std::invalid_argument("half_scores: a and out must be (N,)");
    if (b.shape(0) != 0 && b.shape(0) != N) throw std::invalid_argument("half_scores: b must be empty or (N,)");
#ifdef RF_HALF_SCORES_X86
    if (!cpu_has_simd()) throw std::runtime_error("half_scores: this CPU lacks AVX2/FMA/F16C");
    const int16_t* hp = h.data();
    const float* qp = q.data();
    const float* ap = a.data();
    const float* bp = b.shape(0) ? b.data() : nullptr;
    float* op = out.data();
    nb::gil_scoped_release release;
    const size_t T = std::max<size_t>(1, std::min<size_t>(size_t(std::max(threads, 1)), (N + 65535) / 65536));
    if (T == 1) {
        score_rows(hp, D, qp, ap, bp, qm, op, 0, N);
        return;
    }
    std::vector<std::thread> pool;
    const size_t step = (N + T - 1) / T;
    for (size_t t = 1; t < T; ++t) {
        const size_t lo = std::min(N, t * step), hi = std::min(N, lo + step);
        pool.emplace_back(score_rows, hp, D, qp, ap, bp, qm, op, lo, hi);
    }
    score_rows(hp, D, qp, ap, bp, qm, op, 0, std::min(N, step));
    for (auto& th : pool) th.join();
#else
    (void)qm;
    (void)threads;
    throw std::runtime_error("half_scores: built without x86-64 SIMD support");
#endif
}

}  // namespace

void register_half_scores(nb::module_& m) {
    m.def("half_scores_available", &cpu_has_simd,
          "True if half_scores runs here (an x86-64 CPU with AVX2, FMA and F16C)");
    m.def("half_scores", &half_scores, nb::arg("h"), nb::arg("q"), nb::arg("a"), nb::arg("b"), nb::arg("qm"),
          nb::arg("out"), nb::arg("threads"),
          "out[i] = (h[i] . q) * a[i] + qm * b[i] in float32 over float16 rows h (as int16 bits)");
}
