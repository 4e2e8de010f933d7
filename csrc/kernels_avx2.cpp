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
#include <type_traits>

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

// NR rows x 8 V queries (V = 2, or 1 for a panel of 8): V * NR accumulators
// (12 for NR = kTileRowsAvx2<V>) plus the query vectors and one broadcast fit
// the 16 YMM registers. The dot products of NR rows (row i at base + i * stride, len
// values) with 8 V lanes of a panel W lanes wide, left in acc; shared by the
// plain tile and the projection filter's.
template <int NR, int V>
GDB_AVX2 inline void tile_acc_avx2(const float* base, int64_t stride, int64_t len, const float* panel,
                                   int64_t W, __m256 (&acc)[NR][V]) {
    for (int i = 0; i < NR; ++i)
        for (int k = 0; k < V; ++k) acc[i][k] = _mm256_setzero_ps();
    for (int64_t p = 0; p < len; ++p) {
        const float* x = panel + p * W;
        __m256 xv[V];
        for (int k = 0; k < V; ++k) xv[k] = _mm256_loadu_ps(x + 8 * k);
        for (int i = 0; i < NR; ++i) {
            const __m256 b = _mm256_broadcast_ss(base + i * stride + p);
            for (int k = 0; k < V; ++k) acc[i][k] = _mm256_fmadd_ps(b, xv[k], acc[i][k]);
        }
    }
}

template <int NR, int V>
GDB_AVX2 inline void dots_tile_avx2(const float* base, int64_t stride, int64_t len, const float* panel,
                                    int64_t W, int64_t qp, float* out) {
    __m256 acc[NR][V];
    tile_acc_avx2<NR, V>(base, stride, len, panel, W, acc);
    for (int i = 0; i < NR; ++i)
        for (int k = 0; k < V; ++k) _mm256_storeu_ps(out + i * qp + 8 * k, acc[i][k]);
}

// The last tile of a row range, K rows or fewer: tile(r, nr) with nr = left.
template <int K, class Tile>
GDB_AVX2 inline void tail_tile_avx2(int64_t r, int64_t left, Tile& tile) {
    if constexpr (K >= 1) {
        if (left == K) tile(r, std::integral_constant<int, K>());
        else tail_tile_avx2<K - 1>(r, left, tile);
    }
}

// Rows [0, n_rows) in tiles of NR and one of the rest: tile(r, nr) with nr
// as a std::integral_constant, so each tile height is its own unrolled loop.
template <int NR, class Tile>
GDB_AVX2 inline void row_tiles_avx2(int64_t n_rows, Tile&& tile) {
    int64_t r = 0;
    for (; r + NR <= n_rows; r += NR) tile(r, std::integral_constant<int, NR>());
    tail_tile_avx2<NR - 1>(r, n_rows - r, tile);
}

// Rows per tile for 8 V lanes: 12 accumulators either way, so that enough
// independent FMA chains hide the FMA latency (a panel of 8 with 6 rows
// waited on it).
template <int V>
constexpr int kTileRowsAvx2 = 12 / V;

template <int V>
GDB_AVX2 inline void dots_block_avx2(const float* base, int64_t n_rows, int64_t stride, int64_t len,
                                     const float* xt, int64_t qp, float* out) {
    const int64_t W = panel_width(qp);
    for (int64_t j0 = 0; j0 < qp; j0 += 8 * V) {
        // 8 V lanes of the panel that holds query j0
        const float* panel = xt + panel_offset(j0, len, W);
        row_tiles_avx2<kTileRowsAvx2<V>>(n_rows, [&](int64_t r, auto nr) GDB_AVX2 {
            dots_tile_avx2<decltype(nr)::value, V>(base + r * stride, stride, len, panel, W, qp,
                                                   out + r * qp + j0);
        });
    }
}

}  // namespace

GDB_AVX2 void dots_block_f32_avx2(const float* base, int64_t n_rows, int64_t stride, int64_t len,
                                  const float* xt, int64_t qp, float* out) {
    if (qp >= 16) dots_block_avx2<2>(base, n_rows, stride, len, xt, qp, out);
    else dots_block_avx2<1>(base, n_rows, stride, len, xt, qp, out);
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
    const int64_t words = lane_words(qp);
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

// NR rows x 8 V lanes, as dots_tile_avx2, with the bound formed in registers.
template <int NR, int V>
GDB_AVX2 inline void proj_tile_avx2(const float* z, int64_t J, const float* nrow, const float* rres,
                                    const float* panel, int64_t W, int64_t qp, int64_t j0, const ProjLanes& L,
                                    float* dh, float* umin) {
    __m256 acc[NR][V];
    tile_acc_avx2<NR, V>(z, J, J, panel, W, acc);
    const __m256 two = _mm256_set1_ps(2.0f);
    for (int k = 0; k < V; ++k) {
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

template <int V>
GDB_AVX2 inline void projfilter_avx2(const float* z, int64_t n_rows, int64_t J, const float* nrow,
                                     const float* rres, const float* xt, int64_t qp, const ProjLanes& L,
                                     float* dh, float* umin) {
    const int64_t W = panel_width(qp);
    for (int64_t j0 = 0; j0 < qp; j0 += 8 * V) {
        const float* panel = xt + panel_offset(j0, J, W);
        row_tiles_avx2<kTileRowsAvx2<V>>(n_rows, [&](int64_t r, auto nr) GDB_AVX2 {
            proj_tile_avx2<decltype(nr)::value, V>(z + r * J, J, nrow + r, rres + r, panel, W, qp, j0, L,
                                                   dh + r * qp, umin);
        });
    }
}

}  // namespace

GDB_AVX2 void projfilter_f32_avx2(const float* z, int64_t n_rows, int64_t J, const float* nrow,
                                  const float* rres, const float* xt, int64_t qp, const ProjLanes& L,
                                  float* dh, float* umin) {
    if (qp >= 16) projfilter_avx2<2>(z, n_rows, J, nrow, rres, xt, qp, L, dh, umin);
    else projfilter_avx2<1>(z, n_rows, J, nrow, rres, xt, qp, L, dh, umin);
}

GDB_AVX2 void projkeep_f32_avx2(const float* dh, int64_t n_rows, int64_t qp, const ProjLanes& L,
                                const float* umin, uint64_t* keep) {
    const int64_t words = lane_words(qp);
    for (int64_t w = 0; w < words; ++w) {
        // vectors of 8 lanes in this word: 8, or fewer in a narrow panel
        const int64_t nv = std::min<int64_t>(8, (qp - 64 * w) / 8);
        for (int64_t r = 0; r < n_rows; ++r) {
            uint64_t bits = 0;
            for (int64_t k = 0; k < nv; ++k) {
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
