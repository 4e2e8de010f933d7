// AVX-512 kernels: 16 float lanes, vector loop + masked tail.
//
// The tail uses a masked load instead of a scalar loop: AVX-512 can read the
// last dim % 16 values without touching memory past the row, which matters for
// the 14-value audio frames and the 96-value pose rows alike. Per-function
// target attributes keep the rest of the extension at baseline x86-64.
#include "kernels.h"

#ifdef GESTUREDB_X86
// GCC 12 warns inside its own _mm512_reduce_add_ps (an intentionally undefined
// upper half in _mm512_extractf64x4_pd); the value is never read.
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
// and, once inlined into a loop, inside _mm512_min_ps (its _mm512_undefined_ps
// pass-through operand, unused without a mask)
#pragma GCC diagnostic ignored "-Wuninitialized"
#include <immintrin.h>

#include <algorithm>
#include <cstring>
#include <limits>
#include <type_traits>

#define GDB_AVX512 __attribute__((target("avx512f,avx512dq,avx512bw,avx512vl,fma")))

namespace gesturedb {

namespace {

// Sum of the 16 lanes as the tree ((i, i+8), (i, i+4), (i, i+2), (i, i+1)): the
// order of kernels.h that every ISA's exact kernels follow (written out rather
// than _mm512_reduce_add_ps, whose order is the compiler's to choose).
GDB_AVX512 inline float reduce_tree(__m512 a) {
    const __m256 s8 = _mm256_add_ps(_mm512_castps512_ps256(a), _mm512_extractf32x8_ps(a, 1));
    const __m128 s4 = _mm_add_ps(_mm256_castps256_ps128(s8), _mm256_extractf128_ps(s8, 1));
    const __m128 s2 = _mm_add_ps(s4, _mm_movehl_ps(s4, s4));
    return _mm_cvtss_f32(_mm_add_ss(s2, _mm_shuffle_ps(s2, s2, 1)));
}

// The same tree for 16 vectors at once, lane j of the result = sum of a[j]:
// each level adds the same lane pairs as reduce_tree, only several rows share
// a shuffle, so a row's sum does not depend on whether it went through here.
GDB_AVX512 inline __m512 reduce_tree16(const __m512* a) {
    __m512 l1[8], l2[4], l3[2];
    for (int i = 0; i < 8; ++i)  // rows 2i | 2i+1: lanes i + (i+8)
        l1[i] = _mm512_add_ps(_mm512_shuffle_f32x4(a[2 * i], a[2 * i + 1], 0x44),
                              _mm512_shuffle_f32x4(a[2 * i], a[2 * i + 1], 0xEE));
    for (int i = 0; i < 4; ++i)  // rows 4i..4i+3, one per 128-bit lane: i + (i+4)
        l2[i] = _mm512_add_ps(_mm512_shuffle_f32x4(l1[2 * i], l1[2 * i + 1], 0x88),
                              _mm512_shuffle_f32x4(l1[2 * i], l1[2 * i + 1], 0xDD));
    for (int i = 0; i < 2; ++i)  // i + (i+2)
        l3[i] = _mm512_add_ps(_mm512_shuffle_ps(l2[2 * i], l2[2 * i + 1], 0x44),
                              _mm512_shuffle_ps(l2[2 * i], l2[2 * i + 1], 0xEE));
    // i + (i+1); element 4L + c now holds row 4c + L
    const __m512 s =
        _mm512_add_ps(_mm512_shuffle_ps(l3[0], l3[1], 0x88), _mm512_shuffle_ps(l3[0], l3[1], 0xDD));
    const __m512i to_rows = _mm512_setr_epi32(0, 4, 8, 12, 1, 5, 9, 13, 2, 6, 10, 14, 3, 7, 11, 15);
    return _mm512_permutexvar_ps(to_rows, s);
}

// The 16 partial sums of one row: chunks alternate between two accumulators,
// the tail (dim % 16 values) is a masked load into the second.
GDB_AVX512 inline __m512 l2sq_lanes(const float* row, const float* v, int64_t dim, __mmask16 tail_mask) {
    __m512 acc0 = _mm512_setzero_ps(), acc1 = _mm512_setzero_ps();
    int64_t j = 0;
    for (; j + 32 <= dim; j += 32) {
        const __m512 d0 = _mm512_sub_ps(_mm512_loadu_ps(row + j), _mm512_loadu_ps(v + j));
        const __m512 d1 = _mm512_sub_ps(_mm512_loadu_ps(row + j + 16), _mm512_loadu_ps(v + j + 16));
        acc0 = _mm512_fmadd_ps(d0, d0, acc0);
        acc1 = _mm512_fmadd_ps(d1, d1, acc1);
    }
    if (j + 16 <= dim) {
        const __m512 d0 = _mm512_sub_ps(_mm512_loadu_ps(row + j), _mm512_loadu_ps(v + j));
        acc0 = _mm512_fmadd_ps(d0, d0, acc0);
        j += 16;
    }
    if (tail_mask) {
        const __m512 d1 =
            _mm512_sub_ps(_mm512_maskz_loadu_ps(tail_mask, row + j), _mm512_maskz_loadu_ps(tail_mask, v + j));
        acc1 = _mm512_fmadd_ps(d1, d1, acc1);
    }
    return _mm512_add_ps(acc0, acc1);
}

// Rows are streamed once per step: the hardware prefetcher alone leaves about
// a fifth of the bandwidth unused here (measured: 19.9 -> 16.5 ms for 616k x 96
// on one core, against 13.9 ms for a plain streaming sum), so fetch a few rows
// ahead. Prefetches never fault, so running past the last row is harmless; it
// also warms the next segment's first rows, which the search reads next.
// (Stopping at the last row, to skip the rows no candidate uses, measured slower.)
constexpr int64_t kPrefetchRows = 8;

GDB_AVX512 inline void prefetch_row(const float* row, int64_t dim) {
    const char* p = reinterpret_cast<const char*>(row);
    for (int64_t b = 0; b < dim * int64_t(sizeof(float)); b += 64) _mm_prefetch(p + b, _MM_HINT_T0);
}

}  // namespace

GDB_AVX512 void l2sq_rows_f32_avx512(const float* rows, int64_t n_rows, int64_t dim, const float* v,
                                     float* out) {
    const __mmask16 tail_mask = __mmask16((1u << (dim & 15)) - 1u);
    int64_t r = 0;
    for (; r + 16 <= n_rows; r += 16) {
        __m512 lanes[16];
        for (int i = 0; i < 16; ++i) {
            const float* row = rows + (r + i) * dim;
            prefetch_row(row + kPrefetchRows * dim, dim);
            lanes[i] = l2sq_lanes(row, v, dim, tail_mask);
        }
        _mm512_storeu_ps(out + r, reduce_tree16(lanes));
    }
    for (; r < n_rows; ++r) {
        const float* row = rows + r * dim;
        prefetch_row(row + kPrefetchRows * dim, dim);
        out[r] = reduce_tree(l2sq_lanes(row, v, dim, tail_mask));
    }
}

GDB_AVX512 void cosdots_f32_avx512(const float* base, int64_t n_win, int64_t stride, int64_t len,
                                   const float* q, float* qa, float* aa) {
    const int64_t tail = len & 15;
    const __mmask16 tail_mask = __mmask16((1u << tail) - 1u);
    for (int64_t w = 0; w < n_win; ++w) {
        const float* a = base + w * stride;
        __m512 dot0 = _mm512_setzero_ps(), dot1 = _mm512_setzero_ps();
        __m512 nrm0 = _mm512_setzero_ps(), nrm1 = _mm512_setzero_ps();
        int64_t j = 0;
        for (; j + 32 <= len; j += 32) {
            const __m512 a0 = _mm512_loadu_ps(a + j), a1 = _mm512_loadu_ps(a + j + 16);
            dot0 = _mm512_fmadd_ps(_mm512_loadu_ps(q + j), a0, dot0);
            dot1 = _mm512_fmadd_ps(_mm512_loadu_ps(q + j + 16), a1, dot1);
            nrm0 = _mm512_fmadd_ps(a0, a0, nrm0);
            nrm1 = _mm512_fmadd_ps(a1, a1, nrm1);
        }
        if (j + 16 <= len) {
            const __m512 a0 = _mm512_loadu_ps(a + j);
            dot0 = _mm512_fmadd_ps(_mm512_loadu_ps(q + j), a0, dot0);
            nrm0 = _mm512_fmadd_ps(a0, a0, nrm0);
            j += 16;
        }
        if (tail) {
            const __m512 a1 = _mm512_maskz_loadu_ps(tail_mask, a + j);
            dot1 = _mm512_fmadd_ps(_mm512_maskz_loadu_ps(tail_mask, q + j), a1, dot1);
            nrm1 = _mm512_fmadd_ps(a1, a1, nrm1);
        }
        qa[w] = reduce_tree(_mm512_add_ps(dot0, dot1));
        aa[w] = reduce_tree(_mm512_add_ps(nrm0, nrm1));
    }
}

// --- batched-search filter ---------------------------------------------------

namespace {

// NR rows x 16 V queries (V = 4, or 2 / 1 for a panel of 32 / 16): 4 * NR
// accumulators stay in registers (24 of the 32 for NR = 6) and every broadcast
// row value feeds V FMAs, so the loop is bound by the FMA ports, not by loads.
// The dot products of NR rows (row i at base + i * stride, len values) with
// 16 V lanes of a panel W lanes wide, left in acc; shared by the plain tile and
// the projection filter's.
template <int NR, int V>
GDB_AVX512 inline void tile_acc_avx512(const float* base, int64_t stride, int64_t len, const float* panel,
                                       int64_t W, __m512 (&acc)[NR][V]) {
    for (int i = 0; i < NR; ++i)
        for (int k = 0; k < V; ++k) acc[i][k] = _mm512_setzero_ps();
    for (int64_t p = 0; p < len; ++p) {
        const float* x = panel + p * W;
        __m512 xv[V];
        for (int k = 0; k < V; ++k) xv[k] = _mm512_loadu_ps(x + 16 * k);
        for (int i = 0; i < NR; ++i) {
            const __m512 b = _mm512_set1_ps(base[i * stride + p]);
            for (int k = 0; k < V; ++k) acc[i][k] = _mm512_fmadd_ps(b, xv[k], acc[i][k]);
        }
    }
}

template <int NR, int V>
GDB_AVX512 inline void dots_tile_avx512(const float* base, int64_t stride, int64_t len, const float* panel,
                                        int64_t W, int64_t qp, float* out) {
    __m512 acc[NR][V];
    tile_acc_avx512<NR, V>(base, stride, len, panel, W, acc);
    for (int i = 0; i < NR; ++i)
        for (int k = 0; k < V; ++k) _mm512_storeu_ps(out + i * qp + 16 * k, acc[i][k]);
}

// Rows [0, n_rows) in tiles of 6 and one of the rest: tile(r, nr) with nr
// as a std::integral_constant, so each tile height is its own unrolled loop.
template <class Tile>
GDB_AVX512 inline void row_tiles_avx512(int64_t n_rows, Tile&& tile) {
    constexpr int NR = 6;
    int64_t r = 0;
    for (; r + NR <= n_rows; r += NR) tile(r, std::integral_constant<int, NR>());
    switch (n_rows - r) {
        case 5: tile(r, std::integral_constant<int, 5>()); break;
        case 4: tile(r, std::integral_constant<int, 4>()); break;
        case 3: tile(r, std::integral_constant<int, 3>()); break;
        case 2: tile(r, std::integral_constant<int, 2>()); break;
        case 1: tile(r, std::integral_constant<int, 1>()); break;
        default: break;
    }
}

template <int V>
GDB_AVX512 inline void dots_block_avx512(const float* base, int64_t n_rows, int64_t stride, int64_t len,
                                         const float* xt, int64_t qp, float* out) {
    const int64_t W = panel_width(qp);
    for (int64_t j0 = 0; j0 < qp; j0 += 16 * V) {
        const float* panel = xt + panel_offset(j0, len, W);
        row_tiles_avx512(n_rows, [&](int64_t r, auto nr) GDB_AVX512 {
            dots_tile_avx512<decltype(nr)::value, V>(base + r * stride, stride, len, panel, W, qp,
                                                     out + r * qp + j0);
        });
    }
}

}  // namespace

// A panel of 8 lanes is narrower than one vector: the AVX2 kernels take it
// (every AVX-512 CPU has AVX2, and these are filters: any order is fine).
GDB_AVX512 void dots_block_f32_avx512(const float* base, int64_t n_rows, int64_t stride, int64_t len,
                                      const float* xt, int64_t qp, float* out) {
    if (qp >= 64) dots_block_avx512<4>(base, n_rows, stride, len, xt, qp, out);
    else if (qp == 32) dots_block_avx512<2>(base, n_rows, stride, len, xt, qp, out);
    else if (qp == 16) dots_block_avx512<1>(base, n_rows, stride, len, xt, qp, out);
    else dots_block_f32_avx2(base, n_rows, stride, len, xt, qp, out);
}

namespace {

// Both filters differ only in how (d, b) come from a row and 16 query lanes.
template <class Dist>
GDB_AVX512 inline void filter_avx512(int64_t n_rows, int64_t qp, const uint8_t* ok, float* minhi,
                                     uint64_t* keep, Dist dist) {
    const __m512 inf = _mm512_set1_ps(std::numeric_limits<float>::infinity());
    const __m512 nan = _mm512_set1_ps(std::numeric_limits<float>::quiet_NaN());
    for (int64_t r = 0; r < n_rows; ++r) {
        if (ok != nullptr && !ok[r]) continue;
        for (int64_t j = 0; j < qp; j += 16) {
            __m512 d, b;
            dist(r, j, d, b);
            const __m512 hi = _mm512_add_ps(d, b);
            const __m512 mh = _mm512_loadu_ps(minhi + j);
            // not finite (NaN or inf) now or before: the lane is marked NaN for good
            const __mmask16 bad = _mm512_knot(_mm512_cmp_ps_mask(hi, inf, _CMP_LT_OQ)) |
                                  _mm512_cmp_ps_mask(mh, mh, _CMP_UNORD_Q);
            _mm512_storeu_ps(minhi + j, _mm512_mask_blend_ps(bad, _mm512_min_ps(hi, mh), nan));
        }
    }
    const int64_t words = lane_words(qp);
    std::memset(keep, 0, sizeof(uint64_t) * size_t(n_rows * words));
    for (int64_t r = 0; r < n_rows; ++r) {
        if (ok != nullptr && !ok[r]) continue;
        for (int64_t j = 0; j < qp; j += 16) {
            __m512 d, b;
            dist(r, j, d, b);
            const __mmask16 k =
                _mm512_cmp_ps_mask(_mm512_sub_ps(d, b), _mm512_loadu_ps(minhi + j), _CMP_LE_OQ);
            keep[r * words + j / 64] |= uint64_t(k) << (j % 64);
        }
    }
}

}  // namespace

GDB_AVX512 void l2filter_f32_avx512(const float* c, int64_t n_rows, int64_t qp, const float* nrow,
                                    const float* rrow, const uint8_t* ok, const float* nq, const float* rq,
                                    float eps, float* minhi, uint64_t* keep) {
    if (qp < 16) return l2filter_f32_avx2(c, n_rows, qp, nrow, rrow, ok, nq, rq, eps, minhi, keep);
    const __m512 two = _mm512_set1_ps(2.0f), e = _mm512_set1_ps(eps);
    filter_avx512(n_rows, qp, ok, minhi, keep, [&](int64_t r, int64_t j, __m512& d, __m512& b) GDB_AVX512 {
        const __m512 cc = _mm512_loadu_ps(c + r * qp + j);
        d = _mm512_fnmadd_ps(two, cc, _mm512_add_ps(_mm512_set1_ps(nrow[r]), _mm512_loadu_ps(nq + j)));
        const __m512 s = _mm512_add_ps(_mm512_set1_ps(rrow[r]), _mm512_loadu_ps(rq + j));
        b = _mm512_mul_ps(e, _mm512_mul_ps(s, s));
    });
}

GDB_AVX512 void cosfilter_f32_avx512(const float* c, int64_t n_rows, int64_t qp, const float* nrow,
                                     const float* rrow, const uint8_t* ok, const float* nq, const float* rq,
                                     float eps, float* minhi, uint64_t* keep) {
    if (qp < 16) return cosfilter_f32_avx2(c, n_rows, qp, nrow, rrow, ok, nq, rq, eps, minhi, keep);
    const __m512 one = _mm512_set1_ps(1.0f), e = _mm512_set1_ps(eps);
    filter_avx512(n_rows, qp, ok, minhi, keep, [&](int64_t r, int64_t j, __m512& d, __m512& b) GDB_AVX512 {
        const __m512 cc = _mm512_loadu_ps(c + r * qp + j);
        const __m512 scale = _mm512_mul_ps(_mm512_set1_ps(rrow[r]), _mm512_loadu_ps(rq + j));
        d = _mm512_fnmadd_ps(cc, scale, one);
        b = e;
    });
}

// --- half-precision pose filter ----------------------------------------------

namespace {

// (h - v)^2 accumulated over a binary16 row, 16 lanes.
GDB_AVX512 inline __m512 l2sq_f16_lanes(const uint16_t* row, const float* v, int64_t dim,
                                        __mmask16 tail_mask) {
    __m512 acc0 = _mm512_setzero_ps(), acc1 = _mm512_setzero_ps();
    int64_t j = 0;
    for (; j + 32 <= dim; j += 32) {
        const __m512 h0 = _mm512_cvtph_ps(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(row + j)));
        const __m512 h1 = _mm512_cvtph_ps(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(row + j + 16)));
        const __m512 e0 = _mm512_sub_ps(h0, _mm512_loadu_ps(v + j));
        const __m512 e1 = _mm512_sub_ps(h1, _mm512_loadu_ps(v + j + 16));
        acc0 = _mm512_fmadd_ps(e0, e0, acc0);
        acc1 = _mm512_fmadd_ps(e1, e1, acc1);
    }
    if (j + 16 <= dim) {
        const __m512 h = _mm512_cvtph_ps(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(row + j)));
        const __m512 e = _mm512_sub_ps(h, _mm512_loadu_ps(v + j));
        acc0 = _mm512_fmadd_ps(e, e, acc0);
        j += 16;
    }
    if (tail_mask) {
        const __m512 h = _mm512_cvtph_ps(_mm256_maskz_loadu_epi16(tail_mask, row + j));
        const __m512 e = _mm512_sub_ps(h, _mm512_maskz_loadu_ps(tail_mask, v + j));
        acc1 = _mm512_fmadd_ps(e, e, acc1);
    }
    return _mm512_add_ps(acc0, acc1);
}

GDB_AVX512 inline void prefetch_f16_row(const uint16_t* row, int64_t dim) {
    const char* p = reinterpret_cast<const char*>(row);
    for (int64_t b = 0; b < dim * 2; b += 64) _mm_prefetch(p + b, _MM_HINT_T0);
}

}  // namespace

// Rows of 96 halves are only 192 bytes: a reduction per row would make this
// compute-bound, so rows go 16 at a time through the shared reduction tree.
GDB_AVX512 void l2sq_rows_f16_avx512(const uint16_t* rows, int64_t n_rows, int64_t dim, const float* v,
                                     float* d) {
    const __mmask16 tail_mask = __mmask16((1u << (dim & 15)) - 1u);
    int64_t r = 0;
    for (; r + 16 <= n_rows; r += 16) {
        __m512 acc[16];
        for (int i = 0; i < 16; ++i) {
            const uint16_t* row = rows + (r + i) * dim;
            prefetch_f16_row(row + 2 * kPrefetchRows * dim, dim);
            acc[i] = l2sq_f16_lanes(row, v, dim, tail_mask);
        }
        _mm512_storeu_ps(d + r, reduce_tree16(acc));
    }
    for (; r < n_rows; ++r) {
        const uint16_t* row = rows + r * dim;
        prefetch_f16_row(row + 2 * kPrefetchRows * dim, dim);
        d[r] = reduce_tree(l2sq_f16_lanes(row, v, dim, tail_mask));
    }
}

// 16 frames per block = one vector; partial blocks at the ends of [f0, f1)
// are computed whole and only the frames in range are copied out (and count
// towards the bound's minimum). One body for float32 and binary16 blocks.
namespace {
GDB_AVX512 inline __m512 load16(const float* p) { return _mm512_loadu_ps(p); }
GDB_AVX512 inline __m512 load16(const uint16_t* p) {
    return _mm512_cvtph_ps(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(p)));
}

template <class T>
GDB_AVX512 float l2sq_blocks_avx512(const T* blocks, int64_t f0, int64_t f1, int64_t dim, const float* v,
                                    const float* up, float* out) {
    const float inf = std::numeric_limits<float>::infinity();
    if (f1 <= f0) return inf;
    __m512 umin = _mm512_set1_ps(inf);
    const __m512 ua = _mm512_set1_ps(up ? up[0] : 0.0f), ub = _mm512_set1_ps(up ? up[1] : 0.0f),
                 uc = _mm512_set1_ps(up ? up[2] : 0.0f);
    for (int64_t b = f0 / kFrameBlock; b * kFrameBlock < f1; ++b) {
        const T* blk = blocks + b * kFrameBlock * dim;
        __m512 acc0 = _mm512_setzero_ps(), acc1 = _mm512_setzero_ps();
        int64_t j = 0;
        // two accumulators hide the FMA latency
        for (; j + 2 <= dim; j += 2) {
            const __m512 d0 = _mm512_sub_ps(load16(blk + j * kFrameBlock), _mm512_set1_ps(v[j]));
            const __m512 d1 = _mm512_sub_ps(load16(blk + (j + 1) * kFrameBlock), _mm512_set1_ps(v[j + 1]));
            acc0 = _mm512_fmadd_ps(d0, d0, acc0);
            acc1 = _mm512_fmadd_ps(d1, d1, acc1);
        }
        if (j < dim) {
            const __m512 d0 = _mm512_sub_ps(load16(blk + j * kFrameBlock), _mm512_set1_ps(v[j]));
            acc0 = _mm512_fmadd_ps(d0, d0, acc0);
        }
        const __m512 acc = _mm512_add_ps(acc0, acc1);
        const int64_t lo = std::max(f0, b * kFrameBlock), hi = std::min(f1, (b + 1) * kFrameBlock);
        // lanes [lo, hi) of this block
        const __mmask16 in = __mmask16(((1u << (hi - lo)) - 1u) << (lo - b * kFrameBlock));
        if (in == 0xFFFF) {
            _mm512_storeu_ps(out + (lo - f0), acc);
        } else {
            alignas(64) float tmp[kFrameBlock];
            _mm512_store_ps(tmp, acc);
            for (int64_t f = lo; f < hi; ++f) out[f - f0] = tmp[f - b * kFrameBlock];
        }
        if (up != nullptr) {
            const __m512 bnd =
                _mm512_fmadd_ps(ua, acc, _mm512_fmadd_ps(ub, load16(blk + (dim - 1) * kFrameBlock), uc));
            // min_ps returns its second operand when either is NaN: NaN never lowers it
            umin = _mm512_mask_min_ps(umin, in, bnd, umin);
        }
    }
    return up == nullptr ? inf : _mm512_reduce_min_ps(umin);
}
}  // namespace

GDB_AVX512 float l2sq_blocks_f32_avx512(const float* blocks, int64_t f0, int64_t f1, int64_t dim,
                                        const float* v, const float* up, float* out) {
    return l2sq_blocks_avx512(blocks, f0, f1, dim, v, up, out);
}

GDB_AVX512 float l2sq_blocks_f16_avx512(const uint16_t* blocks, int64_t f0, int64_t f1, int64_t dim,
                                        const float* v, const float* up, float* out) {
    return l2sq_blocks_avx512(blocks, f0, f1, dim, v, up, out);
}

// --- blocked batch: exact pairs and the projection filter ---------------------

// Each pair goes through the same l2sq_lanes and tree as l2sq_rows_f32_avx512
// gives a single row, so the values are bit-identical to it.
GDB_AVX512 void l2sq_pairs_f32_avx512(const float* const* rows, const float* const* vs, int64_t n,
                                      int64_t dim, float* out) {
    const __mmask16 tail_mask = __mmask16((1u << (dim & 15)) - 1u);
    int64_t i = 0;
    for (; i + 16 <= n; i += 16) {
        __m512 lanes[16];
        for (int k = 0; k < 16; ++k) lanes[k] = l2sq_lanes(rows[i + k], vs[i + k], dim, tail_mask);
        _mm512_storeu_ps(out + i, reduce_tree16(lanes));
    }
    for (; i < n; ++i) out[i] = reduce_tree(l2sq_lanes(rows[i], vs[i], dim, tail_mask));
}

// The dot half of cosdots_f32_avx512, instruction for instruction (the same
// two accumulators, masked tail and reduction), so qa is bit-identical.
GDB_AVX512 void cosdots_pairs_f32_avx512(const float* const* wins, const float* const* qs, int64_t n,
                                         int64_t len, float* qa) {
    const int64_t tail = len & 15;
    const __mmask16 tail_mask = __mmask16((1u << tail) - 1u);
    for (int64_t i = 0; i < n; ++i) {
        const float* a = wins[i];
        const float* q = qs[i];
        __m512 dot0 = _mm512_setzero_ps(), dot1 = _mm512_setzero_ps();
        int64_t j = 0;
        for (; j + 32 <= len; j += 32) {
            dot0 = _mm512_fmadd_ps(_mm512_loadu_ps(q + j), _mm512_loadu_ps(a + j), dot0);
            dot1 = _mm512_fmadd_ps(_mm512_loadu_ps(q + j + 16), _mm512_loadu_ps(a + j + 16), dot1);
        }
        if (j + 16 <= len) {
            dot0 = _mm512_fmadd_ps(_mm512_loadu_ps(q + j), _mm512_loadu_ps(a + j), dot0);
            j += 16;
        }
        if (tail)
            dot1 = _mm512_fmadd_ps(_mm512_maskz_loadu_ps(tail_mask, q + j),
                                   _mm512_maskz_loadu_ps(tail_mask, a + j), dot1);
        qa[i] = reduce_tree(_mm512_add_ps(dot0, dot1));
    }
}

namespace {

// NR rows x 64 lanes of the projection filter: the dot products stay in
// registers (4 NR accumulators) and the bound is formed there, so only dh is
// written; umin lives in memory (4 vectors per tile).
template <int NR, int V>
GDB_AVX512 inline void proj_tile_avx512(const float* z, int64_t J, const float* nrow, const float* rres,
                                        const float* panel, int64_t W, int64_t qp, int64_t j0,
                                        const ProjLanes& L, float* dh, float* umin) {
    __m512 acc[NR][V];
    tile_acc_avx512<NR, V>(z, J, J, panel, W, acc);
    const __m512 two = _mm512_set1_ps(2.0f);
    for (int k = 0; k < V; ++k) {
        const int64_t j = j0 + 16 * k;
        const __m512 nq = _mm512_loadu_ps(L.nq + j), aup = _mm512_loadu_ps(L.aup + j);
        const __m512 bup = _mm512_loadu_ps(L.bup + j), cup = _mm512_loadu_ps(L.cup + j);
        __m512 mn = _mm512_loadu_ps(umin + j);
        for (int i = 0; i < NR; ++i) {
            const __m512 d = _mm512_fnmadd_ps(two, acc[i][k], _mm512_add_ps(_mm512_set1_ps(nrow[i]), nq));
            _mm512_storeu_ps(dh + i * qp + j, d);
            const __m512 ub = _mm512_fmadd_ps(aup, d, _mm512_fmadd_ps(bup, _mm512_set1_ps(rres[i]), cup));
            mn = _mm512_min_ps(ub, mn);
        }
        _mm512_storeu_ps(umin + j, mn);
    }
}

template <int V>
GDB_AVX512 inline void projfilter_avx512(const float* z, int64_t n_rows, int64_t J, const float* nrow,
                                         const float* rres, const float* xt, int64_t qp, const ProjLanes& L,
                                         float* dh, float* umin) {
    const int64_t W = panel_width(qp);
    for (int64_t j0 = 0; j0 < qp; j0 += 16 * V) {
        const float* panel = xt + panel_offset(j0, J, W);
        row_tiles_avx512(n_rows, [&](int64_t r, auto nr) GDB_AVX512 {
            proj_tile_avx512<decltype(nr)::value, V>(z + r * J, J, nrow + r, rres + r, panel, W, qp, j0, L,
                                                     dh + r * qp, umin);
        });
    }
}

}  // namespace

GDB_AVX512 void projfilter_f32_avx512(const float* z, int64_t n_rows, int64_t J, const float* nrow,
                                      const float* rres, const float* xt, int64_t qp, const ProjLanes& L,
                                      float* dh, float* umin) {
    if (qp >= 64) projfilter_avx512<4>(z, n_rows, J, nrow, rres, xt, qp, L, dh, umin);
    else if (qp == 32) projfilter_avx512<2>(z, n_rows, J, nrow, rres, xt, qp, L, dh, umin);
    else if (qp == 16) projfilter_avx512<1>(z, n_rows, J, nrow, rres, xt, qp, L, dh, umin);
    else projfilter_f32_avx2(z, n_rows, J, nrow, rres, xt, qp, L, dh, umin);
}

GDB_AVX512 void projkeep_f32_avx512(const float* dh, int64_t n_rows, int64_t qp, const ProjLanes& L,
                                    const float* umin, uint64_t* keep) {
    if (qp < 16) return projkeep_f32_avx2(dh, n_rows, qp, L, umin, keep);
    const int64_t words = lane_words(qp);
    for (int64_t w = 0; w < words; ++w) {
        // vectors of 16 lanes in this word: 4, or fewer in a narrow panel
        const int nv = int(std::min<int64_t>(4, (qp - 64 * w) / 16));
        __m512 alo[4], clo[4], mn[4];
        for (int k = 0; k < nv; ++k) {
            const int64_t j = 64 * w + 16 * k;
            alo[k] = _mm512_loadu_ps(L.alo + j);
            clo[k] = _mm512_loadu_ps(L.clo + j);
            mn[k] = _mm512_loadu_ps(umin + j);
        }
        for (int64_t r = 0; r < n_rows; ++r) {
            uint64_t bits = 0;
            for (int k = 0; k < nv; ++k) {
                const __m512 lb =
                    _mm512_fmsub_ps(alo[k], _mm512_loadu_ps(dh + r * qp + 64 * w + 16 * k), clo[k]);
                bits |= uint64_t(_mm512_cmp_ps_mask(lb, mn[k], _CMP_LE_OQ)) << (16 * k);
            }
            keep[r * words + w] = bits;
        }
    }
}

}  // namespace gesturedb

#endif  // GESTUREDB_X86
