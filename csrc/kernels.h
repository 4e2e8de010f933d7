// Distance kernels of the rank-sum search, one table per instruction set.
//
// Every ISA implements the same functions with the same contract; the scalar
// versions (kernels_scalar.cpp) are plain loops written to be read and are the
// oracle the SIMD versions are tested against. Names follow <op>_<dtype>_<isa>.
//
// Determinism contract (the search relies on it for its tie rules and for
// "batched equals one-by-one"): the value computed for a row or a window
// depends only on the values in it, never on its address, its position in the
// batch or the batch size. Two bit-identical frames therefore always get
// bit-identical distances, so duplicated data produces exact ties.
//
// The exact kernels (l2sq_rows_f32, cosdots_f32 and their _pairs) also give
// the same bits on every ISA, so a search gives the same result on any CPU,
// and the shards of one search on a cluster of mixed CPUs compare like rows of
// one table (a recording and its mirror tie exactly in audio: with distances
// rounded per ISA, the tie broke by the worker that held each shard). They all
// follow one order, the AVX-512 one, for a sum over len terms t_j:
//   two sets of 16 float lanes A and B, all +0; chunk c = [16c, 16c + 16):
//   the full chunks go alternately to A and B (A first), lane l of a chunk
//   being updated acc[l] = fmaf(x_l, y_l, acc[l]) (one rounding); a last,
//   partial chunk goes to B, its missing lanes as fmaf(0, 0, acc[l]);
//   then s[l] = A[l] + B[l], and the tree s[i] + s[i+8], then + [i+4],
//   + [i+2], + [i+1].
// (l2sq: x = y = row_j - v_j, rounded to float; cosdots: x = q_j, y = a_j for
// <q, a> and x = y = a_j for <a, a>.) The scalar versions spell that order out
// with std::fmaf, and the tests compare all ISAs bit for bit.
#pragma once

#include <cstdint>

namespace gesturedb {

// Squared Euclidean distance of each row to one vector:
//   out[r] = sum_j (rows[r * dim + j] - v[j])^2        for r in [0, n_rows)
// rows: (n_rows, dim) row-major, v: (dim,), out: (n_rows,).
using L2sqRowsFn = void (*)(const float* rows, int64_t n_rows, int64_t dim, const float* v, float* out);

// Dot products of sliding windows with one query window:
//   a_w = base + w * stride  (len contiguous values)  for w in [0, n_win)
//   qa[w] = <q, a_w>,  aa[w] = <a_w, a_w>
// Windows may overlap (stride < len): an audio window of n frames of Da values
// starting at frame g is the n * Da floats at audio + g * Da.
using CosDotsFn = void (*)(const float* base, int64_t n_win, int64_t stride, int64_t len, const float* q,
                           float* qa, float* aa);

// Half-precision rows, for the optional pose filter of a single-query step:
//   d[r] = sum_j (h[r][j] - v[j])^2
// with h = rows (IEEE binary16 bit patterns, (n_rows, dim)) converted exactly to
// float32. Only a filter (see half_filter in filters.cpp): any summation order
// is fine, the caller's bound covers float32 rounding of any order.
using L2sqRowsF16Fn = void (*)(const uint16_t* rows, int64_t n_rows, int64_t dim, const float* v, float* d);

// Squared distances of frames stored in blocks of 16 (structure of arrays, for
// the pose projection filter):
//   out[f - f0] = sum_j (blocks[(f/16) * 16 dim + 16 j + f%16] - v[j])^2   for f in [f0, f1)
// A block holds 16 frames column by column, so 16 frames are one vector per
// column and no row needs a horizontal sum. Only a filter (see proj_filter in
// filters.cpp): any summation order and FMA contraction are fine, the caller's
// bound covers the float32 rounding of any order.
// With up = (a, b, c) (or null: returns +inf), also the filter's smallest upper
// bound, fused so that the rows are read once:
//   returns min over f of  a out[f - f0] + b r_f + c,   r_f = the frame's last
//   column (blocks[(f/16) * 16 dim + 16 (dim - 1) + f%16], the residual norm)
// in float32 with any contraction (the caller's bound covers 3 roundings); a
// NaN never lowers the minimum (+inf if every value is NaN).
constexpr int64_t kFrameBlock = 16;
using L2sqBlocksFn = float (*)(const float* blocks, int64_t f0, int64_t f1, int64_t dim, const float* v,
                               const float* up, float* out);
// The same over blocks of IEEE binary16 bit patterns (half the bytes per frame),
// each value converted exactly to float32 first.
using L2sqBlocksF16Fn = float (*)(const uint16_t* blocks, int64_t f0, int64_t f1, int64_t dim, const float* v,
                                  const float* up, float* out);

// --- batched search -------------------------------------------------------
// The batch evaluates many queries against the same rows at once. It uses the
// functions below only as a *filter*: a blocked dot product (GEMM-like, much
// faster per candidate but with a different rounding) gives approximate
// distances with a rigorous error bound, and every candidate that could still
// be the minimum is then recomputed with l2sq_rows_f32 / cosdots_f32 above. So
// the batch returns bit-identical results to one query at a time.

// Lanes: the queries of a block are padded to qp lanes, 8, 16 or 32 (one
// narrow panel) or a multiple of kQueryPanel (panels of 64). The blocked dot
// product's cost is per padded lane, so a call with a few queries takes a
// narrow panel instead of paying for 64 (it did: ~110 ms a call at 617k frames
// whatever the lanes, against ~12 ms for one query's own pass).
constexpr int64_t kQueryPanel = 64;
constexpr int64_t kMinPanel = 8;  // one AVX2 vector
inline int64_t padded_lanes(int64_t n) {
    if (n <= kQueryPanel / 2) {
        int64_t w = kMinPanel;
        while (w < n) w *= 2;
        return w;
    }
    return (n + kQueryPanel - 1) / kQueryPanel * kQueryPanel;
}
// Lanes per panel, and 64-bit words of a bit per lane, for qp padded lanes.
inline int64_t panel_width(int64_t qp) { return qp < kQueryPanel ? qp : kQueryPanel; }
// Where lane j's values start in a packed xt of len values a lane (DotsBlockFn
// below): value p of lane j is at panel_offset(j, len, W) + p * W.
inline int64_t panel_offset(int64_t j, int64_t len, int64_t W) { return (j / W) * W * len + j % W; }
inline int64_t lane_words(int64_t qp) { return (qp + 63) / 64; }

// out[r * qp + j] = sum_p base[r * stride + p] * x[j][p]
//   r < n_rows (rows may overlap: stride < len for audio windows), j < qp,
//   qp a padded lane count (padded_lanes). The queries x are packed in panels
//   of W = panel_width(qp) lanes:
//   x[j][p] = xt[(j / W) * len * W + p * W + j % W], so one panel is a
//   contiguous (len, W) block that stays in L1 while the rows stream past
//   (a (len, qp) layout would map every row of the panel to the same few L1
//   sets once qp * 4 bytes is a multiple of 1 KiB).
using DotsBlockFn = void (*)(const float* base, int64_t n_rows, int64_t stride, int64_t len, const float* xt,
                             int64_t qp, float* out);

// Bound filters over a block c (n_rows, qp) from DotsBlockFn, vectorised across
// the qp queries. For each row r with ok[r] != 0 (ok may be null: all rows):
//   pose  (l2filter):  d = nrow[r] + nq[j] - 2 c[r][j],   b = eps * (rrow[r] + rq[j])^2
//                      (nrow = |row|^2, rrow = |row|, nq = |x|^2, rq = |x|)
//   audio (cosfilter): d = 1 - c[r][j] * rrow[r] * rq[j], b = eps
//                      (rrow = 1/|window| or 0, rq = 1/|q| or 0: zero norms give d = 1)
// minhi[j] (in/out, start at +inf) becomes min(minhi[j], d + b) over the rows,
// or NaN for good once any d + b is not finite (the caller then falls back to
// the exact scan). keep (n_rows, lane_words(qp)) uint64 words, overwritten: bit (r, j)
// is set iff d - b <= minhi[j] after this block.
using FilterFn = void (*)(const float* c, int64_t n_rows, int64_t qp, const float* nrow, const float* rrow,
                          const uint8_t* ok, const float* nq, const float* rq, float eps, float* minhi,
                          uint64_t* keep);

// The exact distances of scattered (row, vector) pairs, for the batch's
// recomputation of what its filter kept:
//   out[i] = what l2sq_rows_f32 of the same ISA gives for rows[i] against vs[i],
//            bit for bit (so the batch decides exactly as the single path)
// rows[i], vs[i]: dim floats each, anywhere.
using L2sqPairsFn = void (*)(const float* const* rows, const float* const* vs, int64_t n, int64_t dim,
                             float* out);

// The dot products of scattered (window, query) pairs, for the audio distance
// of each lane's pre-selected candidate in the batch:
//   qa[i] = the <q, a> that cosdots_f32 of the same ISA gives for window wins[i]
//           and query qs[i] (len values each), bit for bit
// (the window's <a, a> does not depend on the query: the caller computes it
// once per window with cosdots_f32).
using CosDotsPairsFn = void (*)(const float* const* wins, const float* const* qs, int64_t n, int64_t len,
                                float* qa);

// The pose projection filter of the blocked batch (see proj_query in filters.cpp
// for the constants and BlockedBatch::lane_bounds for the bound). Per lane j (qp of them):
struct ProjLanes {
    const float* nq;   // |z_x|^2
    const float* aup;  // upper bound: aup Dh + bup r_f + cup
    const float* bup;
    const float* cup;
    const float* alo;  // lower bound: alo Dh - clo
    const float* clo;
};
// Over rows z (n_rows, J) row-major (a frame's projection z_f) and the query
// panel xt (packed as for DotsBlockFn, len = J):
//   dh[r * qp + j] = nrow[r] + nq[j] - 2 <z_r, x_j>        (any order, FMA or not)
//   umin[j] = min(umin[j], aup[j] dh + bup[j] rres[r] + cup[j])   (in/out)
// nrow = |z_r|^2, or +inf for a row that must not count (dh and the bound are
// then +inf). The caller guarantees that everything stays finite otherwise
// (no NaN handling here; the bound covers the rounding of any order).
using ProjFilterFn = void (*)(const float* z, int64_t n_rows, int64_t J, const float* nrow, const float* rres,
                              const float* xt, int64_t qp, const ProjLanes& lanes, float* dh, float* umin);
// Then keep (n_rows, lane_words(qp)) words, overwritten: bit (r, j) set iff
//   alo[j] dh[r * qp + j] - clo[j] <= umin[j].
using ProjKeepFn = void (*)(const float* dh, int64_t n_rows, int64_t qp, const ProjLanes& lanes,
                            const float* umin, uint64_t* keep);

struct Kernels {
    const char* isa;  // "scalar", "avx2", "avx512"
    L2sqRowsFn l2sq_rows_f32;
    CosDotsFn cosdots_f32;
    DotsBlockFn dots_block_f32;
    FilterFn l2filter_f32;
    FilterFn cosfilter_f32;
    L2sqRowsF16Fn l2sq_rows_f16;
    L2sqBlocksFn l2sq_blocks_f32;
    L2sqBlocksF16Fn l2sq_blocks_f16;
    L2sqPairsFn l2sq_pairs_f32;
    CosDotsPairsFn cosdots_pairs_f32;
    ProjFilterFn projfilter_f32;
    ProjKeepFn projkeep_f32;
};

// IEEE binary16 bit pattern -> float32, exact (every half is a float); portable.
float half_to_float(uint16_t h);

// --- per-ISA implementations (declared here, defined in kernels_<isa>.cpp) --
void l2sq_rows_f32_scalar(const float*, int64_t, int64_t, const float*, float*);
void cosdots_f32_scalar(const float*, int64_t, int64_t, int64_t, const float*, float*, float*);
void dots_block_f32_scalar(const float*, int64_t, int64_t, int64_t, const float*, int64_t, float*);
void l2filter_f32_scalar(const float*, int64_t, int64_t, const float*, const float*, const uint8_t*,
                         const float*, const float*, float, float*, uint64_t*);
void cosfilter_f32_scalar(const float*, int64_t, int64_t, const float*, const float*, const uint8_t*,
                          const float*, const float*, float, float*, uint64_t*);
void l2sq_rows_f16_scalar(const uint16_t*, int64_t, int64_t, const float*, float*);
float l2sq_blocks_f32_scalar(const float*, int64_t, int64_t, int64_t, const float*, const float*, float*);
float l2sq_blocks_f16_scalar(const uint16_t*, int64_t, int64_t, int64_t, const float*, const float*, float*);
void l2sq_pairs_f32_scalar(const float* const*, const float* const*, int64_t, int64_t, float*);
void cosdots_pairs_f32_scalar(const float* const*, const float* const*, int64_t, int64_t, float*);
void projfilter_f32_scalar(const float*, int64_t, int64_t, const float*, const float*, const float*, int64_t,
                           const ProjLanes&, float*, float*);
void projkeep_f32_scalar(const float*, int64_t, int64_t, const ProjLanes&, const float*, uint64_t*);

#if defined(__x86_64__) || defined(_M_X64)
#define GESTUREDB_X86 1
void l2sq_rows_f32_avx2(const float*, int64_t, int64_t, const float*, float*);
void cosdots_f32_avx2(const float*, int64_t, int64_t, int64_t, const float*, float*, float*);
void dots_block_f32_avx2(const float*, int64_t, int64_t, int64_t, const float*, int64_t, float*);
void l2filter_f32_avx2(const float*, int64_t, int64_t, const float*, const float*, const uint8_t*,
                       const float*, const float*, float, float*, uint64_t*);
void cosfilter_f32_avx2(const float*, int64_t, int64_t, const float*, const float*, const uint8_t*,
                        const float*, const float*, float, float*, uint64_t*);
void l2sq_rows_f16_avx2(const uint16_t*, int64_t, int64_t, const float*, float*);
float l2sq_blocks_f32_avx2(const float*, int64_t, int64_t, int64_t, const float*, const float*, float*);
float l2sq_blocks_f16_avx2(const uint16_t*, int64_t, int64_t, int64_t, const float*, const float*, float*);
void l2sq_pairs_f32_avx2(const float* const*, const float* const*, int64_t, int64_t, float*);
void cosdots_pairs_f32_avx2(const float* const*, const float* const*, int64_t, int64_t, float*);
void projfilter_f32_avx2(const float*, int64_t, int64_t, const float*, const float*, const float*, int64_t,
                         const ProjLanes&, float*, float*);
void projkeep_f32_avx2(const float*, int64_t, int64_t, const ProjLanes&, const float*, uint64_t*);
void l2sq_rows_f32_avx512(const float*, int64_t, int64_t, const float*, float*);
void cosdots_f32_avx512(const float*, int64_t, int64_t, int64_t, const float*, float*, float*);
void dots_block_f32_avx512(const float*, int64_t, int64_t, int64_t, const float*, int64_t, float*);
void l2filter_f32_avx512(const float*, int64_t, int64_t, const float*, const float*, const uint8_t*,
                         const float*, const float*, float, float*, uint64_t*);
void cosfilter_f32_avx512(const float*, int64_t, int64_t, const float*, const float*, const uint8_t*,
                          const float*, const float*, float, float*, uint64_t*);
void l2sq_rows_f16_avx512(const uint16_t*, int64_t, int64_t, const float*, float*);
float l2sq_blocks_f32_avx512(const float*, int64_t, int64_t, int64_t, const float*, const float*, float*);
float l2sq_blocks_f16_avx512(const uint16_t*, int64_t, int64_t, int64_t, const float*, const float*, float*);
void l2sq_pairs_f32_avx512(const float* const*, const float* const*, int64_t, int64_t, float*);
void cosdots_pairs_f32_avx512(const float* const*, const float* const*, int64_t, int64_t, float*);
void projfilter_f32_avx512(const float*, int64_t, int64_t, const float*, const float*, const float*, int64_t,
                           const ProjLanes&, float*, float*);
void projkeep_f32_avx512(const float*, int64_t, int64_t, const ProjLanes&, const float*, uint64_t*);
#endif

// --- dispatch (dispatch.cpp) ------------------------------------------------
// The table in use. Chosen once from the CPU (cpuid + xgetbv), overridden by the
// environment variable GESTUREDB_SIMD=scalar|avx2|avx512 at load time and by
// set_simd() at run time. A search reads it once at entry and uses that table
// throughout, so switching mid-search in another thread never mixes ISAs.
const Kernels& active_kernels();

// The table for one ISA name; throws std::invalid_argument naming the ISAs this
// build and CPU can run if `isa` is unknown or unsupported here.
const Kernels& kernels_for(const char* isa);

// Names this build and CPU can run, narrowest first ("scalar" always).
int available_isas(const char** names, int capacity);

// Switch the active table; throws like kernels_for.
void set_simd(const char* isa);

}  // namespace gesturedb
