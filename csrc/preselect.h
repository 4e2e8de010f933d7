// Exact pre-selection of one segment (spec steps 1-3) for one query: the
// allowed candidate with the smallest pre-selection distance, then its other
// distance. The single-query step (step.cpp) and the blocked batch
// (blocked.cpp) both build on these, so a candidate's distances are computed
// by one piece of code whichever path asks.
#pragma once

#include <cmath>
#include <cstdint>

#include "kernels.h"
#include "prefetch.h"
#include "rank.h"
#include "search.h"

namespace gesturedb {

// Cosine distance from the float32 dot products, finished in double.
// Spec: da = 1 - <q,a> / (|q| |a|), and 1 when either norm is 0.
inline double cosine_distance(float qa, float qq, float aa) {
    if (qq == 0.0f || aa == 0.0f) return 1.0;
    return 1.0 - double(qa) / std::sqrt(double(qq) * double(aa));
}

// One query's step inputs as the pre-selection sees them.
struct QueryStep {
    const float* prev;  // (Dp,)
    const float* q;     // (n * Da,)
    float qq;           // <q, q> from cosdots_f32, as every path computes it
    int64_t n;
};

inline float query_norm2(const Kernels& kern, const float* q, int64_t len) {
    float qa = 0.0f, qq = 0.0f;
    kern.cosdots_f32(q, 1, 0, len, q, &qa, &qq);
    return qq;
}

// cosine_distance over arrays, written without branches so that the compiler
// vectorises the division and square root (both exactly rounded, so the values
// are those of cosine_distance).
void cosine_distances(const float* __restrict qa, const float* __restrict qq, const float* __restrict aa,
                      double* __restrict out, int64_t n);

// Spec steps 1-3, first half: the allowed candidate of segment m with the
// smallest pre-selection distance, ties to the smallest s. scratch_a/b hold
// one value per candidate. Returns the candidate index i (s = i + 1) or -1 and
// writes the pre-selection distance into sel.
int64_t preselect_exact(const Kernels& kern, const Database& db, int64_t m, const QueryStep& qs,
                        Preselect pre, const BitsetView& allowed, float* scratch_a, float* scratch_b,
                        Selection& sel);

// The audio distance of the window starting at global frame g (spec step 2).
inline double window_audio_distance(const Kernels& kern, const Database& db, int64_t g, const QueryStep& qs) {
    float qa = 0.0f, aa = 0.0f;
    kern.cosdots_f32(db.audio.row(g), 1, db.audio.cols, qs.n * db.audio.cols, qs.q, &qa, &aa);
    return cosine_distance(qa, qs.qq, aa);
}

// Spec steps 1-3, second half: the other distance of the pre-selected candidate.
inline void complete_other(const Kernels& kern, const Database& db, int64_t m, const QueryStep& qs,
                           Preselect pre, Selection& sel) {
    const int64_t g = db.seg_start[m] + sel.s[m];
    if (pre == Preselect::Pose) {
        sel.da[m] = window_audio_distance(kern, db, g, qs);
    } else {
        kern.l2sq_rows_f32(db.pose.row(g - 1), 1, db.pose.cols, qs.prev, &sel.dp[m]);
    }
}

// complete_other's audio distance for a whole table: the pre-selected start
// starts[m] of every segment (-1: none, then 0 as in the tables) and one query
// window q of n frames. A stream that pre-selected by pose before its audio
// came (the pose pass depends on the previous pose and the bitsets only)
// finishes its step with these, and gets the values every path computes, bit
// for bit, so that ranks and ties are the same.
void audio_distances(const Kernels& kern, const Database& db, const int64_t* starts, const float* q,
                     int64_t n, double* out);

// The windows audio_distances reads, copied out of the database: out (M, n * Da),
// row m the n * Da floats of segment m's candidate starts[m] (zeros where it is
// -1). A stream pre-selected by pose ahead of its speech gathers them then, off
// the latency path, so that its finish reads one contiguous block instead of
// M windows scattered over the whole audio matrix (a TLB and cache miss each).
void gather_windows(const Database& db, const int64_t* starts, int64_t n, float* out);

// audio_distances over gathered windows (M, len), len = n * Da, for one query
// window q (len,): the same values bit for bit (the kernels' values depend on a
// window's values only, never on where it lies), 0 where starts[m] is -1.
void window_distances(const Kernels& kern, const float* windows, const int64_t* starts, int64_t M,
                      int64_t len, const float* q, double* out);

// The rows complete_other will read for segment m: fetched ahead because the
// pre-selected candidates are scattered and each would otherwise be a cache miss.
inline void prefetch_other(const Database& db, int64_t m, const QueryStep& qs, Preselect pre,
                           const Selection& sel) {
    if (sel.s[m] < 0) return;
    const int64_t g = db.seg_start[m] + sel.s[m];
    if (pre == Preselect::Pose)
        prefetch_bytes(db.audio.row(g), qs.n * db.audio.cols * int64_t(sizeof(float)));
    else prefetch_bytes(db.pose.row(g - 1), db.pose.cols * int64_t(sizeof(float)));
}

// The exact pose pre-selection of segment m over the candidates [first, last)
// that a filter (filters.h) kept, in ascending order: the smallest float32
// distance, ties to the smallest s. Returns the candidate index or -1 and
// writes its distance into sel.dp[m].
int64_t argmin_kept(const Kernels& kern, const Database& db, int64_t m, const QueryStep& qs,
                    const int32_t* first, const int32_t* last, Selection& sel);

}  // namespace gesturedb
