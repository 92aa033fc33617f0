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
// walks 4 rows at once, on `threads` threads (std::thread, GIL released).
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
// Sum of the 8 lanes in a fixed order (the same for every row).
__attribute__((target("avx2,fma,f16c"))) inline float lane_sum(__m256 v) {
    const __m128 s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
    const __m128 t = _mm_add_ps(s, _mm_movehl_ps(s, s));
    return _mm_cvtss_f32(_mm_add_ss(t, _mm_shuffle_ps(t, t, 1)));
}

__attribute__((target("avx2,fma,f16c"))) inline __m256 load8(const int16_t* p) {
    return _mm256_cvtph_ps(_mm_loadu_si128(reinterpret_cast<const __m128i*>(p)));
}

// Row i's score from its 8-wide block sums: the lanes summed, then the D % 8 tail in order,
// then the scale and the mean term.
__attribute__((target("avx2,fma,f16c"))) inline void finish_row(const int16_t* h, size_t D, size_t D8,
                                                                 const float* q, const float* a, const float* b,
                                                                 float qm, float* out, size_t i, __m256 acc) {
    float s = lane_sum(acc);
    const int16_t* row = h + i * D;
    for (size_t d = D8; d < D; ++d) s += _cvtsh_ss(static_cast<unsigned short>(row[d])) * q[d];
    float v = s * a[i];
    if (b) v = v + qm * b[i];
    out[i] = v;
}

// Rows [lo, hi): dot products of 8-wide blocks (one accumulator per row, 4 rows at once).
__attribute__((target("avx2,fma,f16c"))) void score_rows(const int16_t* h, size_t D, const float* q,
                                                          const float* a, const float* b, float qm, float* out,
                                                          size_t lo, size_t hi) {
    const size_t D8 = D - D % 8;
    auto finish = [&](size_t i, __m256 acc) { finish_row(h, D, D8, q, a, b, qm, out, i, acc); };
    size_t i = lo;
    for (; i + 4 <= hi; i += 4) {
        const int16_t* r0 = h + i * D;
        __m256 c0 = _mm256_setzero_ps(), c1 = c0, c2 = c0, c3 = c0;
        for (size_t d = 0; d < D8; d += 8) {
            const __m256 qv = _mm256_loadu_ps(q + d);
            c0 = _mm256_fmadd_ps(load8(r0 + d), qv, c0);
            c1 = _mm256_fmadd_ps(load8(r0 + D + d), qv, c1);
            c2 = _mm256_fmadd_ps(load8(r0 + 2 * D + d), qv, c2);
            c3 = _mm256_fmadd_ps(load8(r0 + 3 * D + d), qv, c3);
        }
        finish(i, c0);
        finish(i + 1, c1);
        finish(i + 2, c2);
        finish(i + 3, c3);
    }
    for (; i < hi; ++i) {
        const int16_t* r = h + i * D;
        __m256 c = _mm256_setzero_ps();
        for (size_t d = 0; d < D8; d += 8) c = _mm256_fmadd_ps(load8(r + d), _mm256_loadu_ps(q + d), c);
        finish(i, c);
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
