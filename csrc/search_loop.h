// The search loop's pieces that the batch (batch.cpp, blocked.cpp) reuses, so
// a batched query runs exactly the loop of a single search: how many steps a
// query takes, how a step is written out, the argument checks, and the loop.
#pragma once

#include <cstdint>

#include "search.h"

namespace gesturedb {

// Steps of a query of T frames at window N: t = 0, N, 2N, ...
inline int64_t n_steps(int64_t T, int64_t window) { return (T + window - 1) / window; }

// Writes step i (at output frame t) of a search's outputs.
inline void write_step(const SearchOutput& out, int64_t i, int64_t t, const StepResult& r) {
    out.segment[i] = r.segment;
    out.start[i] = r.start;
    out.frame[i] = r.frame;
    out.length[i] = r.length;
    out.out_frame[i] = t;
    out.pose_dist[i] = r.pose_dist;
    out.audio_dist[i] = r.audio_dist;
    out.pose_rank[i] = r.pose_rank;
    out.audio_rank[i] = r.audio_rank;
    out.n_candidates[i] = r.n_candidates;
}

// The bitsets query q searches under: its own (BatchQuery::allowed) or the batch's.
inline AllowedSchedule query_allowed(const BatchQuery& q, const AllowedSchedule& batch) {
    if (!q.has_allowed) return batch;
    AllowedSchedule s;
    if (q.allowed.all()) return s;
    s.words = q.allowed.words;
    s.n_words = q.allowed.n_words;
    s.n_rows = 1;
    return s;
}

// Throws std::invalid_argument unless query, window, k and allowed fit db.
void check_search_args(const Database& db, Span2<const float> query, int64_t window, int64_t k,
                       const AllowedSchedule& allowed);

// The steps of one query on engine; returns -1 or the step that found no
// candidate (rank_sum_search's contract).
int64_t run_search(StepEngine& engine, const Database& db, Span2<const float> query, const float* init_pose,
                   int64_t window, int64_t k, Preselect preselect, const AllowedSchedule& allowed,
                   const bool* exclude, const SearchOutput& out);

}  // namespace gesturedb
