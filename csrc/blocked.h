// The blocked batch: many queries' searches (or one step's pre-selection
// tables) with each candidate row of the database read once per block of
// queries and step. Owns BlockedBatch: its set-up (blocked_setup.cpp: per-frame
// norms, the projection rows, the error bounds of its filter) and its run
// (blocked.cpp: the step loop and its pieces). batch.cpp decides when a batch
// takes this path; the results are always those of the single-query path.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include "filters.h"
#include "kernels.h"
#include "search.h"

namespace gesturedb {

// Blocked batch: a block of queries advances step by step together. At each
// step the queries whose window is full (n = N) form the lanes of a panel (8,
// 16, 32 or whole panels of 64 lanes, as the step's lanes need); per
// segment one blocked dot product gives every lane's approximate distance to
// every candidate, the bound filter keeps the candidates that could still be
// the lane's minimum, and those are recomputed with the exact kernels in
// ascending s. Queries in their last, partial window take the single path.
//
// With a pose projection (Database::proj) and pose pre-selection, the blocked
// dot product runs over the J projected columns instead of the Dp pose columns
// (a quarter of the work at J = 24, Dp = 96) and the filter is the projection's
// bound of proj_filter, widened by the error of the blocked form (see
// lane_bounds): the same candidates-that-could-win are recomputed exactly, so
// the results stay those of the single path.
class BlockedBatch {
public:
    static constexpr int64_t kRowTile = 128;  // candidates per dot-product call
    // From this many lanes a step prefetches every entry pose of the next
    // segment (prefetch_rows), below it only the rows its filter kept
    static constexpr int64_t kPrefetchLanes = kQueryPanel;
    // Projection filter: rows or lanes with |z|^2 above this take the exact scan,
    // so that no value of the blocked bound can overflow (see lane_bounds).
    static constexpr double kProjBig = 1e30;

    // The projection in the layout of the blocked dot product (rows of J
    // values), |z_f|^2 and r_f per frame. It does not depend on the window
    // length, so a BatchPlan builds it once for every window it serves.
    struct ProjRows {
        std::vector<float> zrow, pnrow, rres;
        std::vector<int64_t> n_bad;  // (F + 1,): frames before f whose row the filter cannot use
        double zmax = 0.0, eps = 0.0;
    };

    // proj_rows: the database's ProjRows when already built (null: built here).
    BlockedBatch(const Kernels& kern, const Database& db, int64_t window, Preselect pre, int threads,
                 std::shared_ptr<const ProjRows> proj_rows = nullptr);

    const std::shared_ptr<const ProjRows>& proj_rows() const { return pr_; }

    // Runs every query of the block through all its steps (allowed: the
    // bitset of each step; a query with its own, BatchQuery::allowed, uses that).
    //
    // Lanes with different bitsets: per segment, the lanes whose bitsets allow
    // the same candidates of it form a group, and each group is one pass of the
    // blocked filter over the segment's rows (which stay in cache from one
    // group to the next): lanes that differ only where the segment has nothing
    // of theirs share a pass, and the database is still streamed once a step.
    void run(BatchQuery* const* block, int64_t nq, const AllowedSchedule& allowed_steps) const;

private:
    // One run()'s lanes, query panel and scratch, allocated once per block.
    struct Run;

    // The pieces of run(), in the order each step calls them.
    int64_t take_lanes(Run& r, int64_t step, const AllowedSchedule& allowed_steps) const;
    void lane_views(Run& r, const BitsetView& shared) const;
    void mark_lanes(Run& r) const;
    void load_panel(Run& r) const;
    void preselect_segment(Run& r, int64_t m) const;
    void segment_group(Run& r, int64_t m, const BitsetView& allowed, const uint8_t* okp,
                       const uint64_t* group) const;
    bool allowed_candidates(int64_t m, const BitsetView& allowed, uint8_t* ok, const uint8_t*& okp) const;
    bool segment_lanes(Run& r, int64_t m, const uint64_t* group) const;
    bool sparse_enough(const Run& r, const uint8_t* okp, int64_t n_cand) const;
    void filter_tile(Run& r, int64_t m, int64_t i0, int64_t nr, const uint8_t* okp) const;
    void recompute_kept(Run& r, int64_t m, int64_t i0, int64_t nr) const;
    int64_t choose_candidates(Run& r, int64_t m, const BitsetView& allowed) const;
    void other_distances(Run& r, int64_t m, int64_t n_fin) const;
    void rank_lanes(Run& r, int64_t step) const;

    // The set-up and the bounds (blocked_setup.cpp).
    static std::shared_ptr<const ProjRows> build_proj_rows(const Database& db, int threads);
    static void lane_defaults(std::vector<float>& par, int64_t qp);
    bool lane_bounds(const ProjQuery& pq, std::vector<float>& par, int64_t qp, int64_t l) const;

    // Helpers of the run (blocked.cpp).
    static void mark_excluded(const bool* ex, int64_t M, int64_t l, int64_t words, uint64_t* ex_bits);
    static int64_t collect_pairs(const uint64_t* __restrict keep, const uint64_t* __restrict live, int64_t nr,
                                 int64_t words, int32_t* __restrict pair_lane, int32_t* __restrict pair_r);
    static bool tile_has_row(const uint8_t* okp, int64_t i0, int64_t nr);
    void prefetch_rows(int64_t m, bool other, int64_t nl) const;
    int64_t max_seg_len() const;
    void exact_update_audio(int64_t m, int64_t i, const QueryStep& qs, int64_t l, std::vector<int64_t>& best,
                            std::vector<double>& best_da) const;
    void finish(BatchQuery* bq, int64_t step, int64_t t, const StepResult& r, const float*& prev) const;

    const Kernels& kern_;
    const Database& db_;
    int64_t N_;
    Preselect pre_;
    std::vector<float> nrow_, rrow_;
    std::vector<float> wnorm_;  // pose mode: <a, a> of the N-frame audio window at each frame
    float eps_ = 0.0f;
    // the projection filter (proj_: pose pre-selection with Database::proj)
    bool proj_ = false;
    std::shared_ptr<const ProjRows> pr_;
    std::vector<uint8_t> seg_bad_;
};

}  // namespace gesturedb
