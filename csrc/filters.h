// Bounded filters of the pose pre-selection: they read fewer bytes per
// candidate than the float32 pose rows (binary16 rows, or the J columns of the
// projection in Database::proj) and keep, in ascending order, every candidate
// that could still be its segment's exact minimum; argmin_kept (preselect.h)
// then recomputes only those. Results do not change: each bound is derived at
// its definition in filters.cpp. Both return false when a value is not finite
// (the bound then says nothing and the caller scans the segment exactly).
// The blocked batch widens ProjQuery's bounds for its lanes (blocked.cpp).
#pragma once

#include <cstdint>
#include <vector>

#include "kernels.h"
#include "preselect.h"
#include "search.h"

namespace gesturedb {

// Pose pre-selection of segment m through the half-precision copy of pose
// (Database::pose_f16) against prev = qs.prev with x_norm = ||prev||: appends
// the kept candidates to `kept`. dh: scratch, one value per candidate.
bool half_filter(const Kernels& kern, const Database& db, int64_t m, const QueryStep& qs, double x_norm,
                 const BitsetView& allowed, float* dh, std::vector<int32_t>& kept);

// The query side of the projection filter: z_x = (U^T (x - mean), r_x) in
// double, its float32 copy for the filter kernel, and the constants of the
// bounds (see proj_filter).
struct ProjQuery {
    std::vector<float> zx;  // (J,)
    float a_lo = 0, c_lo = 0, a_up = 0, b_up = 0, c_up = 0;
    bool ok = false;  // false: not finite, every segment is scanned exactly
};

// The ProjQuery of the previous pose x (Dp,).
ProjQuery proj_query(const Database& db, const float* x);

// Pose pre-selection filter of segment m through the projection (see
// Database::proj): the smallest upper bound Umin over the allowed candidates,
// then every candidate whose lower bound is <= Umin is kept (ascending). The
// exact minimum of the kept ones (ties to the smallest s) is the exact answer:
// the winner's exact distance is <= Umin and its lower bound <= that.
// Returns false when a value is not finite; the caller then scans exactly.
bool proj_filter(const Kernels& kern, const Database& db, int64_t m, const QueryStep& qs, const ProjQuery& pq,
                 const BitsetView& allowed, float* dh, std::vector<int32_t>& kept);

}  // namespace gesturedb
