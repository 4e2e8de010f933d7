// AVX2 + FMA kernels: 8 float lanes; the exact ones (l2sq_rows, cosdots) hold
// kernels.h's 16-lane order in register pairs with a masked tail, the filters
// run a vector loop and a scalar tail.
//
// Compiled with per-function target attributes (not -mavx2 for the file) so the
// rest of the extension keeps baseline x86-64 code and runs on any CPU; these
// functions are only called after dispatch.cpp has seen AVX2 and FMA in cpuid
// and the OS saving YMM state in xgetbv.
#include "kernels.h"

#ifdef GESTUREDB_X86
#include <immintrin.h>

#include <algorithm>
#include <cstring>
#include <limits>

#define GDB_AVX2 __attribute__((target("avx2,fma")))

namespace gesturedb {
namespace {

GDB_AVX2 inline float hsum256(__m256 v) {
    __m128 s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
    s = _mm_add_ps(s, _mm_movehl_ps(s, s));
    s = _mm_add_ss(s, _mm_movehdup_ps(s));
    return _mm_cvtss_f32(s);
}

}  // namespace

// The exact kernels in the order of kernels.h: its 16-lane sets A and B are
// two registers each here (lanes 0-7, 8-15), and the tail a masked load
// (vmaskmovps reads nothing where the mask is off, so no read past the row).
namespace {

// first n of 8 lanes set, n in [0, 8]: load 8 ints from kFirst + 8 - n
alignas(32) constexpr int32_t kFirst[16] = {-1, -1, -1, -1, -1, -1, -1, -1, 0, 0, 0, 0, 0, 0, 0, 0};

GDB_AVX2 inline __m256i first_lanes(int64_t n) {
    n = n < 0 ? 0 : (n > 8 ? 8 : n);
    return _mm256_loadu_si256(reinterpret_cast<const __m256i*>(kFirst + 8 - n));
}

// The tail masks of a length: the lanes 0-7 and 8-15 of the last, partial chunk.
struct TailMasks {
    int64_t tail;
    __m256i m0, m1;
};

GDB_AVX2 inline TailMasks tail_masks(int64_t len) {
    const int64_t tail = len & 15;
    return {tail, first_lanes(tail), first_lanes(tail - 8)};
}

// (A + B) of kernels.h summed by its tree: lanes (i, i+8), then hsum256's (i, i+4), (i, i+2), (i, i+1)
GDB_AVX2 inline float canonical_total(__m256 a0, __m256 a1, __m256 b0, __m256 b1) {
    return hsum256(_mm256_add_ps(_mm256_add_ps(a0, b0), _mm256_add_ps(a1, b1)));
}

GDB_AVX2 inline float l2sq_one(const float* row, const float* v, int64_t dim, const TailMasks& t) {
    __m256 a0 = _mm256_setzero_ps(), a1 = _mm256_setzero_ps();
    __m256 b0 = _mm256_setzero_ps(), b1 = _mm256_setzero_ps();
    int64_t j = 0;
    for (; j + 32 <= dim; j += 32) {
        const __m256 d0 = _mm256_sub_ps(_mm256_loadu_ps(row + j), _mm256_loadu_ps(v + j));
        const __m256 d1 = _mm256_sub_ps(_mm256_loadu_ps(row + j + 8), _mm256_loadu_ps(v + j + 8));
        const __m256 d2 = _mm256_sub_ps(_mm256_loadu_ps(row + j + 16), _mm256_loadu_ps(v + j + 16));
        const __m256 d3 = _mm256_sub_ps(_mm256_loadu_ps(row + j + 24), _mm256_loadu_ps(v + j + 24));
        a0 = _mm256_fmadd_ps(d0, d0, a0);
        a1 = _mm256_fmadd_ps(d1, d1, a1);
        b0 = _mm256_fmadd_ps(d2, d2, b0);
        b1 = _mm256_fmadd_ps(d3, d3, b1);
    }
    if (j + 16 <= dim) {
        const __m256 d0 = _mm256_sub_ps(_mm256_loadu_ps(row + j), _mm256_loadu_ps(v + j));
        const __m256 d1 = _mm256_sub_ps(_mm256_loadu_ps(row + j + 8), _mm256_loadu_ps(v + j + 8));
        a0 = _mm256_fmadd_ps(d0, d0, a0);
        a1 = _mm256_fmadd_ps(d1, d1, a1);
        j += 16;
    }
    if (t.tail) {
        const __m256 d2 = _mm256_sub_ps(_mm256_maskload_ps(row + j, t.m0), _mm256_maskload_ps(v + j, t.m0));
        const __m256 d3 =
            _mm256_sub_ps(_mm256_maskload_ps(row + j + 8, t.m1), _mm256_maskload_ps(v + j + 8, t.m1));
        b0 = _mm256_fmadd_ps(d2, d2, b0);
        b1 = _mm256_fmadd_ps(d3, d3, b1);
    }
    return canonical_total(a0, a1, b0, b1);
}

// <q, a> (and <a, a> when nrm is not null) of one window
GDB_AVX2 inline float cosdots_one(const float* a, const float* q, int64_t len, const TailMasks& t,
                                  float* nrm) {
    __m256 a0 = _mm256_setzero_ps(), a1 = _mm256_setzero_ps(), b0 = _mm256_setzero_ps(),
           b1 = _mm256_setzero_ps();
    __m256 n0 = _mm256_setzero_ps(), n1 = _mm256_setzero_ps(), m0 = _mm256_setzero_ps(),
           m1 = _mm256_setzero_ps();
    int64_t j = 0;
    for (; j + 32 <= len; j += 32) {
        const __m256 x0 = _mm256_loadu_ps(a + j), x1 = _mm256_loadu_ps(a + j + 8);
        const __m256 x2 = _mm256_loadu_ps(a + j + 16), x3 = _mm256_loadu_ps(a + j + 24);
        a0 = _mm256_fmadd_ps(_mm256_loadu_ps(q + j), x0, a0);
        a1 = _mm256_fmadd_ps(_mm256_loadu_ps(q + j + 8), x1, a1);
        b0 = _mm256_fmadd_ps(_mm256_loadu_ps(q + j + 16), x2, b0);
        b1 = _mm256_fmadd_ps(_mm256_loadu_ps(q + j + 24), x3, b1);
        if (nrm) {
            n0 = _mm256_fmadd_ps(x0, x0, n0);
            n1 = _mm256_fmadd_ps(x1, x1, n1);
            m0 = _mm256_fmadd_ps(x2, x2, m0);
            m1 = _mm256_fmadd_ps(x3, x3, m1);
        }
    }
    if (j + 16 <= len) {
        const __m256 x0 = _mm256_loadu_ps(a + j), x1 = _mm256_loadu_ps(a + j + 8);
        a0 = _mm256_fmadd_ps(_mm256_loadu_ps(q + j), x0, a0);
        a1 = _mm256_fmadd_ps(_mm256_loadu_ps(q + j + 8), x1, a1);
        if (nrm) {
            n0 = _mm256_fmadd_ps(x0, x0, n0);
            n1 = _mm256_fmadd_ps(x1, x1, n1);
        }
        j += 16;
    }
    if (t.tail) {
        const __m256 x2 = _mm256_maskload_ps(a + j, t.m0), x3 = _mm256_maskload_ps(a + j + 8, t.m1);
        b0 = _mm256_fmadd_ps(_mm256_maskload_ps(q + j, t.m0), x2, b0);
        b1 = _mm256_fmadd_ps(_mm256_maskload_ps(q + j + 8, t.m1), x3, b1);
        if (nrm) {
            m0 = _mm256_fmadd_ps(x2, x2, m0);
            m1 = _mm256_fmadd_ps(x3, x3, m1);
        }
    }
    if (nrm) *nrm = canonical_total(n0, n1, m0, m1);
    return canonical_total(a0, a1, b0, b1);
}

}  // namespace

GDB_AVX2 void l2sq_rows_f32_avx2(const float* rows, int64_t n_rows, int64_t dim, const float* v, float* out) {
    const TailMasks t = tail_masks(dim);
    for (int64_t r = 0; r < n_rows; ++r) out[r] = l2sq_one(rows + r * dim, v, dim, t);
}

GDB_AVX2 void cosdots_f32_avx2(const float* base, int64_t n_win, int64_t stride, int64_t len, const float* q,
                               float* qa, float* aa) {
    const TailMasks t = tail_masks(len);
    for (int64_t w = 0; w < n_win; ++w) qa[w] = cosdots_one(base + w * stride, q, len, t, aa + w);
}

// --- batched-search filter ---------------------------------------------------

namespace {

// NR rows x 16 queries: 2 * NR accumulators (12 for NR = 6) plus two query
// vectors and one broadcast fit the 16 YMM registers.
// The dot products of NR rows (row i at base + i * stride, len values) with 16
// panel lanes, left in acc; shared by the plain tile and the projection filter's.
template <int NR>
GDB_AVX2 inline void tile_acc_avx2(const float* base, int64_t stride, int64_t len, const float* panel,
                                   __m256 (&acc)[NR][2]) {
    for (int i = 0; i < NR; ++i) acc[i][0] = acc[i][1] = _mm256_setzero_ps();
    for (int64_t p = 0; p < len; ++p) {
        const float* x = panel + p * 64;
        const __m256 x0 = _mm256_loadu_ps(x), x1 = _mm256_loadu_ps(x + 8);
        for (int i = 0; i < NR; ++i) {
            const __m256 b = _mm256_broadcast_ss(base + i * stride + p);
            acc[i][0] = _mm256_fmadd_ps(b, x0, acc[i][0]);
            acc[i][1] = _mm256_fmadd_ps(b, x1, acc[i][1]);
        }
    }
}

template <int NR>
GDB_AVX2 inline void dots_tile_avx2(const float* base, int64_t stride, int64_t len, const float* panel,
                                    int64_t qp, float* out) {
    __m256 acc[NR][2];
    tile_acc_avx2<NR>(base, stride, len, panel, acc);
    for (int i = 0; i < NR; ++i) {
        _mm256_storeu_ps(out + i * qp, acc[i][0]);
        _mm256_storeu_ps(out + i * qp + 8, acc[i][1]);
    }
}

}  // namespace

GDB_AVX2 void dots_block_f32_avx2(const float* base, int64_t n_rows, int64_t stride, int64_t len,
                                  const float* xt, int64_t qp, float* out) {
    constexpr int NR = 6;
    for (int64_t j0 = 0; j0 < qp; j0 += 16) {
        // 16 lanes of the 64-lane panel that holds query j0
        const float* panel = xt + (j0 / 64) * 64 * len + (j0 % 64);
        int64_t r = 0;
        for (; r + NR <= n_rows; r += NR)
            dots_tile_avx2<NR>(base + r * stride, stride, len, panel, qp, out + r * qp + j0);
        const float* b = base + r * stride;
        float* o = out + r * qp + j0;
        switch (n_rows - r) {
            case 5: dots_tile_avx2<5>(b, stride, len, panel, qp, o); break;
            case 4: dots_tile_avx2<4>(b, stride, len, panel, qp, o); break;
            case 3: dots_tile_avx2<3>(b, stride, len, panel, qp, o); break;
            case 2: dots_tile_avx2<2>(b, stride, len, panel, qp, o); break;
            case 1: dots_tile_avx2<1>(b, stride, len, panel, qp, o); break;
            default: break;
        }
    }
}

namespace {

template <class Dist>
GDB_AVX2 inline void filter_avx2(int64_t n_rows, int64_t qp, const uint8_t* ok, float* minhi, uint64_t* keep,
                                 Dist dist) {
    const __m256 inf = _mm256_set1_ps(std::numeric_limits<float>::infinity());
    const __m256 nan = _mm256_set1_ps(std::numeric_limits<float>::quiet_NaN());
    for (int64_t r = 0; r < n_rows; ++r) {
        if (ok != nullptr && !ok[r]) continue;
        for (int64_t j = 0; j < qp; j += 8) {
            __m256 d, b;
            dist(r, j, d, b);
            const __m256 hi = _mm256_add_ps(d, b);
            const __m256 mh = _mm256_loadu_ps(minhi + j);
            // not finite (NaN or inf) now or before: the lane is marked NaN for good
            const __m256 bad =
                _mm256_or_ps(_mm256_cmp_ps(hi, inf, _CMP_NLT_UQ), _mm256_cmp_ps(mh, mh, _CMP_UNORD_Q));
            _mm256_storeu_ps(minhi + j, _mm256_blendv_ps(_mm256_min_ps(hi, mh), nan, bad));
        }
    }
    const int64_t words = qp / 64;
    std::memset(keep, 0, sizeof(uint64_t) * size_t(n_rows * words));
    for (int64_t r = 0; r < n_rows; ++r) {
        if (ok != nullptr && !ok[r]) continue;
        for (int64_t j = 0; j < qp; j += 8) {
            __m256 d, b;
            dist(r, j, d, b);
            const __m256 k = _mm256_cmp_ps(_mm256_sub_ps(d, b), _mm256_loadu_ps(minhi + j), _CMP_LE_OQ);
            keep[r * words + j / 64] |= uint64_t(unsigned(_mm256_movemask_ps(k))) << (j % 64);
        }
    }
}

}  // namespace

GDB_AVX2 void l2filter_f32_avx2(const float* c, int64_t n_rows, int64_t qp, const float* nrow,
                                const float* rrow, const uint8_t* ok, const float* nq, const float* rq,
                                float eps, float* minhi, uint64_t* keep) {
    const __m256 two = _mm256_set1_ps(2.0f), e = _mm256_set1_ps(eps);
    filter_avx2(n_rows, qp, ok, minhi, keep, [&](int64_t r, int64_t j, __m256& d, __m256& b) GDB_AVX2 {
        const __m256 cc = _mm256_loadu_ps(c + r * qp + j);
        d = _mm256_fnmadd_ps(two, cc, _mm256_add_ps(_mm256_set1_ps(nrow[r]), _mm256_loadu_ps(nq + j)));
        const __m256 s = _mm256_add_ps(_mm256_set1_ps(rrow[r]), _mm256_loadu_ps(rq + j));
        b = _mm256_mul_ps(e, _mm256_mul_ps(s, s));
    });
}

GDB_AVX2 void cosfilter_f32_avx2(const float* c, int64_t n_rows, int64_t qp, const float*, const float* rrow,
                                 const uint8_t* ok, const float*, const float* rq, float eps, float* minhi,
                                 uint64_t* keep) {
    const __m256 one = _mm256_set1_ps(1.0f), e = _mm256_set1_ps(eps);
    filter_avx2(n_rows, qp, ok, minhi, keep, [&](int64_t r, int64_t j, __m256& d, __m256& b) GDB_AVX2 {
        const __m256 cc = _mm256_loadu_ps(c + r * qp + j);
        const __m256 scale = _mm256_mul_ps(_mm256_set1_ps(rrow[r]), _mm256_loadu_ps(rq + j));
        d = _mm256_fnmadd_ps(cc, scale, one);
        b = e;
    });
}

// --- half-precision pose filter ----------------------------------------------

__attribute__((target("avx2,fma,f16c"))) void l2sq_rows_f16_avx2(const uint16_t* rows, int64_t n_rows,
                                                                 int64_t dim, const float* v, float* d) {
    for (int64_t r = 0; r < n_rows; ++r) {
        const uint16_t* row = rows + r * dim;
        // fetch ahead: the rows are streamed (3 cache lines for 96 halves)
        const char* ahead = reinterpret_cast<const char*>(row + 16 * dim);
        for (int64_t b = 0; b < dim * 2; b += 64) _mm_prefetch(ahead + b, _MM_HINT_T0);
        __m256 acc0 = _mm256_setzero_ps(), acc1 = _mm256_setzero_ps();
        int64_t j = 0;
        for (; j + 16 <= dim; j += 16) {
            const __m256 h0 = _mm256_cvtph_ps(_mm_loadu_si128(reinterpret_cast<const __m128i*>(row + j)));
            const __m256 h1 = _mm256_cvtph_ps(_mm_loadu_si128(reinterpret_cast<const __m128i*>(row + j + 8)));
            const __m256 e0 = _mm256_sub_ps(h0, _mm256_loadu_ps(v + j));
            const __m256 e1 = _mm256_sub_ps(h1, _mm256_loadu_ps(v + j + 8));
            acc0 = _mm256_fmadd_ps(e0, e0, acc0);
            acc1 = _mm256_fmadd_ps(e1, e1, acc1);
        }
        float a = hsum256(_mm256_add_ps(acc0, acc1));
        for (; j < dim; ++j) {
            const float e = _cvtsh_ss(row[j]) - v[j];
            a += e * e;
        }
        d[r] = a;
    }
}

// 16 frames per block = two vectors of 8; a partial block at either end of
// [f0, f1) is computed whole and only its frames in range are copied out (and
// count towards the bound's minimum). One body for float32 and binary16
// blocks: only the load differs.
namespace {
#define GDB_AVX2_F16C __attribute__((target("avx2,fma,f16c")))
GDB_AVX2_F16C inline __m256 load8(const float* p) { return _mm256_loadu_ps(p); }
GDB_AVX2_F16C inline __m256 load8(const uint16_t* p) {
    return _mm256_cvtph_ps(_mm_loadu_si128(reinterpret_cast<const __m128i*>(p)));
}

template <class T>
GDB_AVX2_F16C float l2sq_blocks_avx2(const T* blocks, int64_t f0, int64_t f1, int64_t dim, const float* v,
                                     const float* up, float* out) {
    const float inf = std::numeric_limits<float>::infinity();
    if (f1 <= f0) return inf;
    alignas(32) float tmp[kFrameBlock];
    alignas(32) float ubt[kFrameBlock];
    __m256 umin0 = _mm256_set1_ps(inf), umin1 = umin0;
    const __m256 ua = _mm256_set1_ps(up ? up[0] : 0.0f), ub = _mm256_set1_ps(up ? up[1] : 0.0f),
                 uc = _mm256_set1_ps(up ? up[2] : 0.0f);
    float tail_min = inf;
    for (int64_t b = f0 / kFrameBlock; b * kFrameBlock < f1; ++b) {
        const T* blk = blocks + b * kFrameBlock * dim;
        __m256 acc0 = _mm256_setzero_ps(), acc1 = _mm256_setzero_ps();
        for (int64_t j = 0; j < dim; ++j) {
            const __m256 x = _mm256_set1_ps(v[j]);
            const __m256 d0 = _mm256_sub_ps(load8(blk + j * kFrameBlock), x);
            const __m256 d1 = _mm256_sub_ps(load8(blk + j * kFrameBlock + 8), x);
            acc0 = _mm256_fmadd_ps(d0, d0, acc0);
            acc1 = _mm256_fmadd_ps(d1, d1, acc1);
        }
        __m256 b0 = _mm256_setzero_ps(), b1 = b0;
        if (up != nullptr) {
            const T* r = blk + (dim - 1) * kFrameBlock;
            b0 = _mm256_fmadd_ps(ua, acc0, _mm256_fmadd_ps(ub, load8(r), uc));
            b1 = _mm256_fmadd_ps(ua, acc1, _mm256_fmadd_ps(ub, load8(r + 8), uc));
        }
        const int64_t lo = std::max(f0, b * kFrameBlock), hi = std::min(f1, (b + 1) * kFrameBlock);
        if (lo == b * kFrameBlock && hi == lo + kFrameBlock) {
            _mm256_storeu_ps(out + (lo - f0), acc0);
            _mm256_storeu_ps(out + (lo - f0) + 8, acc1);
            // min_ps returns its second operand when either is NaN: NaN never lowers it
            umin0 = _mm256_min_ps(b0, umin0);
            umin1 = _mm256_min_ps(b1, umin1);
        } else {
            _mm256_store_ps(tmp, acc0);
            _mm256_store_ps(tmp + 8, acc1);
            _mm256_store_ps(ubt, b0);
            _mm256_store_ps(ubt + 8, b1);
            for (int64_t f = lo; f < hi; ++f) {
                out[f - f0] = tmp[f - b * kFrameBlock];
                const float u = ubt[f - b * kFrameBlock];
                tail_min = u < tail_min ? u : tail_min;
            }
        }
    }
    if (up == nullptr) return inf;
    alignas(32) float m[8];
    _mm256_store_ps(m, _mm256_min_ps(umin0, umin1));
    for (float x : m) tail_min = x < tail_min ? x : tail_min;
    return tail_min;
}
}  // namespace

GDB_AVX2_F16C float l2sq_blocks_f32_avx2(const float* blocks, int64_t f0, int64_t f1, int64_t dim,
                                         const float* v, const float* up, float* out) {
    return l2sq_blocks_avx2(blocks, f0, f1, dim, v, up, out);
}

GDB_AVX2_F16C float l2sq_blocks_f16_avx2(const uint16_t* blocks, int64_t f0, int64_t f1, int64_t dim,
                                         const float* v, const float* up, float* out) {
    return l2sq_blocks_avx2(blocks, f0, f1, dim, v, up, out);
}

// --- blocked batch: exact pairs and the projection filter ---------------------

// The single-row kernel itself for each pair: bit-identical by construction.
GDB_AVX2 void l2sq_pairs_f32_avx2(const float* const* rows, const float* const* vs, int64_t n, int64_t dim,
                                  float* out) {
    const TailMasks t = tail_masks(dim);
    for (int64_t i = 0; i < n; ++i) out[i] = l2sq_one(rows[i], vs[i], dim, t);
}

GDB_AVX2 void cosdots_pairs_f32_avx2(const float* const* wins, const float* const* qs, int64_t n, int64_t len,
                                     float* qa) {
    const TailMasks t = tail_masks(len);
    for (int64_t i = 0; i < n; ++i) qa[i] = cosdots_one(wins[i], qs[i], len, t, nullptr);
}

namespace {

// NR rows x 16 lanes, as dots_tile_avx2, with the bound formed in registers.
template <int NR>
GDB_AVX2 inline void proj_tile_avx2(const float* z, int64_t J, const float* nrow, const float* rres,
                                    const float* panel, int64_t qp, int64_t j0, const ProjLanes& L, float* dh,
                                    float* umin) {
    __m256 acc[NR][2];
    tile_acc_avx2<NR>(z, J, J, panel, acc);
    const __m256 two = _mm256_set1_ps(2.0f);
    for (int k = 0; k < 2; ++k) {
        const int64_t j = j0 + 8 * k;
        const __m256 nq = _mm256_loadu_ps(L.nq + j), aup = _mm256_loadu_ps(L.aup + j);
        const __m256 bup = _mm256_loadu_ps(L.bup + j), cup = _mm256_loadu_ps(L.cup + j);
        __m256 mn = _mm256_loadu_ps(umin + j);
        for (int i = 0; i < NR; ++i) {
            const __m256 d = _mm256_fnmadd_ps(two, acc[i][k], _mm256_add_ps(_mm256_set1_ps(nrow[i]), nq));
            _mm256_storeu_ps(dh + i * qp + j, d);
            const __m256 ub = _mm256_fmadd_ps(aup, d, _mm256_fmadd_ps(bup, _mm256_set1_ps(rres[i]), cup));
            mn = _mm256_min_ps(ub, mn);
        }
        _mm256_storeu_ps(umin + j, mn);
    }
}

}  // namespace

GDB_AVX2 void projfilter_f32_avx2(const float* z, int64_t n_rows, int64_t J, const float* nrow,
                                  const float* rres, const float* xt, int64_t qp, const ProjLanes& L,
                                  float* dh, float* umin) {
    constexpr int NR = 6;
    for (int64_t j0 = 0; j0 < qp; j0 += 16) {
        const float* panel = xt + (j0 / 64) * 64 * J + (j0 % 64);
        int64_t r = 0;
        for (; r + NR <= n_rows; r += NR)
            proj_tile_avx2<NR>(z + r * J, J, nrow + r, rres + r, panel, qp, j0, L, dh + r * qp, umin);
        const float* zr = z + r * J;
        float* o = dh + r * qp;
        switch (n_rows - r) {
            case 5: proj_tile_avx2<5>(zr, J, nrow + r, rres + r, panel, qp, j0, L, o, umin); break;
            case 4: proj_tile_avx2<4>(zr, J, nrow + r, rres + r, panel, qp, j0, L, o, umin); break;
            case 3: proj_tile_avx2<3>(zr, J, nrow + r, rres + r, panel, qp, j0, L, o, umin); break;
            case 2: proj_tile_avx2<2>(zr, J, nrow + r, rres + r, panel, qp, j0, L, o, umin); break;
            case 1: proj_tile_avx2<1>(zr, J, nrow + r, rres + r, panel, qp, j0, L, o, umin); break;
            default: break;
        }
    }
}

GDB_AVX2 void projkeep_f32_avx2(const float* dh, int64_t n_rows, int64_t qp, const ProjLanes& L,
                                const float* umin, uint64_t* keep) {
    const int64_t words = qp / 64;
    for (int64_t w = 0; w < words; ++w) {
        for (int64_t r = 0; r < n_rows; ++r) {
            uint64_t bits = 0;
            for (int k = 0; k < 8; ++k) {
                const int64_t j = 64 * w + 8 * k;
                const __m256 lb = _mm256_fmsub_ps(
                    _mm256_loadu_ps(L.alo + j), _mm256_loadu_ps(dh + r * qp + j), _mm256_loadu_ps(L.clo + j));
                const __m256 m = _mm256_cmp_ps(lb, _mm256_loadu_ps(umin + j), _CMP_LE_OQ);
                bits |= uint64_t(unsigned(_mm256_movemask_ps(m))) << (8 * k);
            }
            keep[r * words + w] = bits;
        }
    }
}

}  // namespace gesturedb

#endif  // GESTUREDB_X86
