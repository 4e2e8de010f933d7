// Exact pre-selection of one segment (preselect.h): the scans that define the
// result every filter must reproduce.
#include "preselect.h"
#include "allowed.h"
#include "order.h"

#include <algorithm>
#include <cstring>

namespace gesturedb {

void cosine_distances(const float* __restrict qa, const float* __restrict qq, const float* __restrict aa,
                      double* __restrict out, int64_t n) {
    for (int64_t i = 0; i < n; ++i) {
        const double q2 = qq[i], a2 = aa[i];
        const double den = std::sqrt(q2 * a2);
        const double d = 1.0 - double(qa[i]) / den;
        // 1 when either norm is 0, by masks: a ?: here is control flow to the vectoriser
        const uint64_t zero = -uint64_t((q2 == 0.0) | (a2 == 0.0));
        uint64_t bits, one_bits;
        const double one = 1.0;
        std::memcpy(&bits, &d, 8);
        std::memcpy(&one_bits, &one, 8);
        bits = (bits & ~zero) | (one_bits & zero);
        std::memcpy(&out[i], &bits, 8);
    }
}

int64_t preselect_exact(const Kernels& kern, const Database& db, int64_t m, const QueryStep& qs,
                        Preselect pre, const BitsetView& allowed, float* scratch_a, float* scratch_b,
                        Selection& sel) {
    const int64_t n = qs.n;
    const int64_t n_cand = db.seg_len[m] - n;  // s = 1 .. seg_len - n
    if (n_cand < 1) return -1;
    const int64_t seg0 = db.seg_start[m];
    const int64_t Dp = db.pose.cols, Da = db.audio.cols;
    int64_t best = -1;
    if (pre == Preselect::Pose) {
        float best_dp = 0.0f;
        for_each_allowed_run(allowed, seg0 + 1, n_cand, n - 1, [&](int64_t i0, int64_t i1) {
            // the entry frame of candidate i is g - 1 = seg0 + i
            kern.l2sq_rows_f32(db.pose.row(seg0 + i0), i1 - i0, Dp, qs.prev, scratch_a);
            for (int64_t i = i0; i < i1; ++i) {
                const float d = scratch_a[i - i0];
                // strict: an equal distance later in the segment never wins
                if (best < 0 || nan_last_less(d, best_dp)) {
                    best = i;
                    best_dp = d;
                }
            }
        });
        if (best >= 0) sel.dp[m] = best_dp;
    } else {
        double best_da = 0.0;
        for_each_allowed_run(allowed, seg0 + 1, n_cand, n - 1, [&](int64_t i0, int64_t i1) {
            // the window of candidate i starts at g = seg0 + 1 + i
            kern.cosdots_f32(db.audio.row(seg0 + 1 + i0), i1 - i0, Da, n * Da, qs.q, scratch_a, scratch_b);
            for (int64_t i = i0; i < i1; ++i) {
                const double d = cosine_distance(scratch_a[i - i0], qs.qq, scratch_b[i - i0]);
                if (best < 0 || nan_last_less(d, best_da)) {
                    best = i;
                    best_da = d;
                }
            }
        });
        if (best >= 0) sel.da[m] = best_da;
    }
    return best;
}

void audio_distances(const Kernels& kern, const Database& db, const int64_t* starts, const float* q,
                     int64_t n, double* out) {
    const int64_t M = db.n_segments(), Da = db.audio.cols;
    QueryStep qs{nullptr, q, query_norm2(kern, q, n * Da), n};
    // the candidates are scattered over the database: fetch a few segments ahead
    constexpr int64_t kAhead = 32;
    auto fetch = [&](int64_t m) {
        if (starts[m] >= 0)
            prefetch_bytes(db.audio.row(db.seg_start[m] + starts[m]), n * Da * int64_t(sizeof(float)));
    };
    for (int64_t m = 0; m < std::min(M, kAhead); ++m) fetch(m);
    for (int64_t m = 0; m < M; ++m) {
        if (m + kAhead < M) fetch(m + kAhead);
        out[m] = starts[m] < 0 ? 0.0 : window_audio_distance(kern, db, db.seg_start[m] + starts[m], qs);
    }
}

void gather_windows(const Database& db, const int64_t* starts, int64_t n, float* out) {
    const int64_t M = db.n_segments(), len = n * db.audio.cols;
    const int64_t bytes = len * int64_t(sizeof(float));
    // the windows are scattered over the database: fetch a few segments ahead
    constexpr int64_t kAhead = 32;
    auto fetch = [&](int64_t m) {
        if (starts[m] >= 0) prefetch_bytes(db.audio.row(db.seg_start[m] + starts[m]), bytes);
    };
    for (int64_t m = 0; m < std::min(M, kAhead); ++m) fetch(m);
    for (int64_t m = 0; m < M; ++m) {
        if (m + kAhead < M) fetch(m + kAhead);
        float* row = out + m * len;
        if (starts[m] < 0) std::memset(row, 0, size_t(bytes));
        else std::memcpy(row, db.audio.row(db.seg_start[m] + starts[m]), size_t(bytes));
    }
}

void window_distances(const Kernels& kern, const float* windows, const int64_t* starts, int64_t M,
                      int64_t len, const float* q, double* out) {
    // rows in chunks that keep the dot products on the stack; cosdots_f32 runs
    // over consecutive rows with stride len, as over a segment's windows
    constexpr int64_t kRows = 256;
    float qa[kRows], aa[kRows], qq[kRows];
    std::fill(qq, qq + kRows, query_norm2(kern, q, len));
    for (int64_t m0 = 0; m0 < M; m0 += kRows) {
        const int64_t r = std::min(kRows, M - m0);
        kern.cosdots_f32(windows + m0 * len, r, len, len, q, qa, aa);
        cosine_distances(qa, qq, aa, out + m0, r);
        for (int64_t i = 0; i < r; ++i)
            if (starts[m0 + i] < 0) out[m0 + i] = 0.0;
    }
}

int64_t argmin_kept(const Kernels& kern, const Database& db, int64_t m, const QueryStep& qs,
                    const int32_t* first, const int32_t* last, Selection& sel) {
    const int64_t seg0 = db.seg_start[m];
    int64_t best = -1;
    float best_dp = 0.0f;
    // the kept rows as pairs (the same bits as l2sq_rows_f32 row by row, kernels.h):
    // l2sq_rows_f32 prefetches rows ahead of each call, which for one kept row
    // of a few in a segment fetched another row that is mostly never read (the
    // step prefetches the kept rows themselves, step.cpp)
    constexpr int64_t kChunk = 64;
    const float* rows[kChunk];
    const float* vs[kChunk];
    float d[kChunk];
    for (const int32_t* c0 = first; c0 != last;) {
        const int64_t n = std::min<int64_t>(kChunk, last - c0);
        for (int64_t i = 0; i < n; ++i) {
            rows[i] = db.pose.row(seg0 + c0[i]);
            vs[i] = qs.prev;
        }
        kern.l2sq_pairs_f32(rows, vs, n, db.pose.cols, d);
        for (int64_t i = 0; i < n; ++i)
            if (best < 0 || nan_last_less(d[i], best_dp)) {
                best = c0[i];
                best_dp = d[i];
            }
        c0 += n;
    }
    if (best >= 0) sel.dp[m] = best_dp;
    return best;
}

}  // namespace gesturedb
