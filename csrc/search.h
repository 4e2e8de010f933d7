// The rank-sum motion-matching search (Habibie et al. 2022, Sec. 3.1) over
// spans. Knows nothing of Python; the exact semantics are in
// ../shared/spec/search.md and summarised at each step below.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include "kernels.h"
#include "span.h"

namespace gesturedb {

enum class Preselect { Pose = 0, Audio = 1 };

struct Database {
    Span2<const float> pose;         // (F, Dp) pose feature per frame
    Span2<const float> audio;        // (F, Da) audio feature per frame
    Span1<const int64_t> seg_start;  // (M,) first global frame of each segment
    Span1<const int64_t> seg_len;    // (M,) frames in each segment
    // Optional (F, Dp) binary16 copy of pose (round-to-nearest), data null when
    // absent. Pose pre-selection then streams these half-size rows and bounds
    // the distance each row can have in float32; only rows that may still be a
    // segment's minimum are read in float32. Results do not change.
    Span2<const uint16_t> pose_f16;
    // Optional projection of pose (data null when absent), a bounded filter
    // for pose pre-selection that reads J = proj_dim instead of Dp floats per frame:
    //   z_f = (U^T (P[f] - mean), ||(I - U U^T)(P[f] - mean)||)   (J values)
    // stored in blocks of 16 frames (kernels.h, l2sq_blocks): proj is
    // (ceil(F / 16), 16 J), value j of frame f at proj(f / 16, 16 j + f % 16).
    // with U = proj_basis (Dp, J-1) orthonormal columns (float64) and
    // proj_max_norm >= max_f ||P[f] - mean||. The squared distance of a frame
    // to prev then lies in [|z_f - z_x|^2, |z_f - z_x|^2 + 4 r_f r_x]; the step
    // keeps the candidates whose lower bound can reach the smallest upper bound
    // and computes only those exactly on P. Results do not change.
    // proj_f16 instead of proj: the same blocks in binary16 (half the bytes per
    // frame), each value the round-to-nearest of the float64 projection; the
    // filter's bound then covers that rounding too. At most one of the two is set.
    Span2<const float> proj;
    Span2<const uint16_t> proj_f16;
    int64_t proj_dim = 0;
    Span2<const double> proj_basis;
    Span1<const double> proj_mean;
    double proj_max_norm = 0.0;

    bool has_proj() const { return proj.data != nullptr || proj_f16.data != nullptr; }
    // value j of frame f of the projection, whichever precision holds it
    float proj_value(int64_t f, int64_t j) const;
    int64_t n_frames() const { return pose.rows; }
    int64_t n_segments() const { return seg_start.size; }
};

// Throws std::invalid_argument when the shapes disagree or a segment reaches
// outside [0, F). The Python layer checks the same things with friendlier
// messages; this is the backstop that keeps the C++ from reading out of bounds.
void check_database(const Database& db);

struct StepOptions {
    int64_t k = 1;  // 1-based rank of the choice
    Preselect preselect = Preselect::Pose;
    BitsetView allowed;             // empty view: every frame allowed
    const bool* exclude = nullptr;  // (M,) true = segment excluded; may be null
    // StepEngine::preselect only: false leaves the pre-selected candidates' other
    // distance out (0 in the table). A pose pre-selection made ahead of its audio
    // (StepBatch.speculate) is finished by audio_distances once the audio has
    // come; its zero window's distances were a third of its cost, read for nothing.
    bool other = true;
};

struct StepResult {
    bool found = false;
    int64_t segment = -1;      // m
    int64_t start = -1;        // s, offset of the window in the segment (>= 1)
    int64_t frame = -1;        // g = seg_start[m] + s, first global frame of the window
    int64_t length = 0;        // n, frames in the window
    double pose_dist = 0.0;    // ||P[g-1] - prev||^2
    double audio_dist = 0.0;   // 1 - cos(query window, audio window)
    int64_t pose_rank = -1;    // rp, 0-based
    int64_t audio_rank = -1;   // ra, 0-based
    int64_t n_candidates = 0;  // segments left after pre-selection
};

// Output arrays of one search, each (S,) with S = ceil(T / window).
struct SearchOutput {
    int64_t* segment;
    int64_t* start;
    int64_t* frame;
    int64_t* length;
    int64_t* out_frame;
    double* pose_dist;
    double* audio_dist;
    int64_t* pose_rank;
    int64_t* audio_rank;
    int64_t* n_candidates;
};

// `allowed` for a whole search: nothing, one bitset for every step, or one
// bitset per step (a control schedule, rows = number of steps).
struct AllowedSchedule {
    const uint64_t* words = nullptr;
    int64_t n_words = 0;
    int64_t n_rows = 0;  // 0: no mask; 1 with per_step false: shared
    bool per_step = false;

    BitsetView at(int64_t step) const {
        if (words == nullptr) return {};
        return {per_step ? words + step * n_words : words, n_words};
    }
};

// Evaluates steps against one database. Holds the per-segment pre-selection
// results and per-thread scratch so that a whole search allocates once.
class StepEngine {
public:
    // threads: worker threads for one step (parallel over segments); 1 runs
    // everything on the calling thread.
    StepEngine(const Kernels& kernels, const Database& db, int threads);
    ~StepEngine();
    StepEngine(const StepEngine&) = delete;
    StepEngine& operator=(const StepEngine&) = delete;

    // One step: prev (Dp,), query window (n, Da) contiguous, 1 <= n.
    StepResult step(const float* prev, const float* query, int64_t n, const StepOptions& opt);

    // Spec steps 1-3 only, the table a sharded search merges: per segment m
    // (M,) the pre-selected start s (-1 when the segment has no allowed
    // candidate), its pose distance (float32, as the ranking compares it) and
    // audio distance. Ranks computed over the rows of several shards' tables
    // (ties by global segment index) are exactly those of one database.
    void preselect(const float* prev, const float* query, int64_t n, const StepOptions& opt, int64_t* start,
                   float* pose_dist, double* audio_dist);

private:
    struct Impl;
    std::unique_ptr<Impl> impl_;
};

// Spec steps 4-5 over a pre-selection table of M rows (start -1: no
// candidate), e.g. several shards' tables concatenated in global segment order.
struct TableRank {
    int64_t segment = -1;  // -1 when no row has a candidate
    int64_t pose_rank = -1;
    int64_t audio_rank = -1;
    int64_t n_candidates = 0;
};
TableRank rank_table(const int64_t* start, const float* pose_dist, const double* audio_dist, int64_t M,
                     int64_t k);

// The first n rows of each of Q tables of M rows (row-major, start -1: no
// candidate) by pose distance and by audio distance, in the order the ranker
// ranks them (order key, then row): a shard's top lists. by_pose, by_audio:
// (Q, n), -1 past a table's candidates; n_cand: (Q,) rows with a candidate.
void table_top_lists(const int64_t* start, const float* pose_dist, const double* audio_dist, int64_t Q,
                     int64_t M, int64_t n, int32_t* by_pose, int32_t* by_audio, int64_t* n_cand);

// A whole search of query (T, Da) from init_pose (Dp,), steps at t = 0, N, 2N...
// Returns -1 on success, else the index of the step that found no candidate
// (entries from that step on are left unwritten).
int64_t rank_sum_search(const Kernels& kernels, const Database& db, Span2<const float> query,
                        const float* init_pose, int64_t window, int64_t k, Preselect preselect,
                        const AllowedSchedule& allowed, const bool* exclude, const SearchOutput& out,
                        int threads);

// One query of a batch: its own audio, initial pose, k, exclusion row and outputs.
struct BatchQuery {
    Span2<const float> audio;  // (T_i, Da)
    const float* init_pose;    // (Dp,)
    int64_t k;
    const bool* exclude;  // (M,) or null
    // The query's own bitset, in place of the batch's for every step (has_allowed;
    // allowed.all(): every frame): clients with different controls in one batch.
    // Queries whose bitsets are the same words pointer share the blocked filter's
    // passes (the bindings point equal rows at one).
    bool has_allowed = false;
    BitsetView allowed;
    SearchOutput out;          // (S_i,) each
    int64_t failed_step = -1;  // written: -1 or the failing step
    // Set by preselect_batch: the query's one window is pre-selected into
    // these (M,) rows (as StepEngine::preselect writes them), not ranked.
    int64_t* table_s = nullptr;
    float* table_dp = nullptr;
    double* table_da = nullptr;
    bool table_other = true;  // StepOptions::other for this query's table
};

// Auto takes the blocked path from this many queries per thread (a block per
// thread): at 617k frames a block of 1 query cost 1.8-2 single-query passes
// (its filter reads float32 rows, and fetches the rows it keeps as it finds
// them), of 2 as much as 2 passes, of 3 0.85-0.9 of 3 passes, of 4 0.7-0.8
// of 4 (benchmarks/RESULTS.md, "Narrow panels").
constexpr int64_t kBlockedMinQueries = 3;
// Queries from which Auto takes the blocked path with `threads` threads
// (threads > 0): enough that each thread's block holds kBlockedMinQueries.
inline int64_t blocked_min_queries(int threads) { return (kBlockedMinQueries - 1) * int64_t(threads) + 1; }

// How a batch is evaluated; every method returns exactly what rank_sum_search
// returns for each query alone.
enum class BatchMethod {
    Auto,      // Blocked when the ISA has block kernels and each thread's block
               // would hold >= kBlockedMinQueries queries
    Blocked,   // blocks of queries share each candidate row (blocked dot product
               // as a bounded filter, exact recomputation of what it keeps)
    PerQuery,  // each query runs the single-query path
};

// Runs every query exactly as rank_sum_search would, in parallel over blocks of
// queries (one level of parallelism: nothing inside a block is threaded).
void rank_sum_search_batch(const Kernels& kernels, const Database& db, std::vector<BatchQuery>& queries,
                           int64_t window, Preselect preselect, const AllowedSchedule& allowed, int threads,
                           BatchMethod method = BatchMethod::Auto);

// Spec steps 1-3 of one step for many queries, on one database over many
// calls: query i's window is queries[i].audio (all with the same number of
// rows n), its previous pose queries[i].init_pose, and its (M,) table goes to
// queries[i].table_*, each row exactly StepEngine::preselect's. The blocked
// method shares each candidate row across a block of queries, as in
// rank_sum_search_batch; this is what a sharded batch merges (top lists per
// query). Its per-frame set-up (the audio windows' norms, the projection
// rows: a pass over the database, about 0.4 s at 2.5M frames) is built on
// first use for each window length and kept, so a caller that pre-selects
// step after step (a shard on its worker) pays it once. The database's arrays
// must outlive the plan. preselect() may be called from several threads at once.
class BatchPlan {
public:
    BatchPlan(const Kernels& kernels, const Database& db, Preselect preselect);
    ~BatchPlan();
    BatchPlan(const BatchPlan&) = delete;
    BatchPlan& operator=(const BatchPlan&) = delete;

    void preselect(std::vector<BatchQuery>& queries, const AllowedSchedule& allowed, int threads,
                   BatchMethod method = BatchMethod::Auto);
    // Window lengths whose blocked set-up is kept.
    int64_t n_setups() const;

private:
    struct Impl;
    std::unique_ptr<Impl> impl_;
};

}  // namespace gesturedb
