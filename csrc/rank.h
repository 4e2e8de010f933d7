// Ranking (spec steps 4-5): from each segment's pre-selected candidate to the
// chosen one. Owns Selection, the per-segment table the pre-selection fills and
// the ranker reads, and Ranker, which a step, a blocked batch and a sharded
// merge (rank_table, table_top_lists in search.h) all rank with, so every path
// breaks ties the same way.
#pragma once

#include <cstdint>
#include <utility>
#include <vector>

#include "search.h"

namespace gesturedb {

// Pre-selection results of one query at one step, indexed by segment.
struct Selection {
    int64_t* s;  // chosen offset, or -1 when the segment has no allowed candidate
    float* dp;   // its pose distance
    double* da;  // its audio distance
};

// Spec steps 4-5 over a Selection.
//
// Only the first k segments in (R, rp) order matter, and R = rp + ra >= L for
// every segment outside the L best by dp or outside the L best by da. So the
// ranker first ranks just those two top-L lists (a partial selection, O(K)):
// if the k-th of the segments in both lists has R < L, no other segment can
// come before it and the answer is exact. Otherwise (or when the last segment
// is asked for) it ranks everything with the radix sort. With independent
// ranks about L^2 / K segments land in both lists, so L = 256 almost always
// settles k <= 15 for K ~ 10^4 in a fraction of the full ranking's time.
class Ranker {
public:
    static constexpr int32_t kTop = 256;

    // The chosen segment of a Selection over db's segments (StepResult.found
    // false when none has a candidate); n is the window length it reports.
    StepResult rank(const Database& db, const Selection& sel, int64_t n, int64_t k);

private:
    bool top_lists(int32_t K, int64_t k, int32_t& c, int64_t& rp_out, int64_t& ra_out);
    void full(int32_t K, int64_t k, int32_t& c, int64_t& rp_out, int64_t& ra_out);

    std::vector<int32_t> cand_, ord_dp_, ord_da_, tmp_, rp_, ra_;
    std::vector<uint32_t> kdp_, hist_;
    std::vector<uint64_t> kda_, rkey_, pdp_, known_;
    std::vector<std::pair<uint64_t, int32_t>> pda_;
};

}  // namespace gesturedb
