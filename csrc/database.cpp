// The database a search reads (search.h, struct Database): its one accessor
// and check_database, the C++ backstop on its shapes, so that no later stage
// can read outside the arrays whatever the caller passed.
#include "search.h"

#include <limits>
#include <stdexcept>
#include <string>

namespace gesturedb {

float Database::proj_value(int64_t f, int64_t j) const {
    const int64_t i = kFrameBlock * j + f % kFrameBlock;
    return proj.data != nullptr ? proj(f / kFrameBlock, i) : half_to_float(proj_f16(f / kFrameBlock, i));
}

void check_database(const Database& db) {
    const int64_t F = db.pose.rows;
    if (db.audio.rows != F) {
        throw std::invalid_argument("audio: expected " + std::to_string(F) + " rows like pose; got " +
                                    std::to_string(db.audio.rows));
    }
    if (db.pose.cols < 1 || db.audio.cols < 1) {
        throw std::invalid_argument("pose/audio: expected at least one feature column");
    }
    if (db.seg_len.size != db.seg_start.size) {
        throw std::invalid_argument("seg_len: expected " + std::to_string(db.seg_start.size) +
                                    " entries like seg_start; got " + std::to_string(db.seg_len.size));
    }
    if (F > int64_t(std::numeric_limits<int32_t>::max()) ||
        db.seg_start.size > int64_t(std::numeric_limits<int32_t>::max())) {
        throw std::invalid_argument("database: expected fewer than 2^31 frames and segments");
    }
    if (db.pose_f16.data != nullptr && (db.pose_f16.rows != F || db.pose_f16.cols != db.pose.cols)) {
        throw std::invalid_argument("pose_f16: expected the shape of pose (" + std::to_string(F) + ", " +
                                    std::to_string(db.pose.cols) + "); got (" +
                                    std::to_string(db.pose_f16.rows) + ", " +
                                    std::to_string(db.pose_f16.cols) + ")");
    }
    if (db.proj.data != nullptr && db.proj_f16.data != nullptr)
        throw std::invalid_argument("pose_proj: expected float32 or binary16 blocks, not both");
    if (db.has_proj()) {
        const int64_t J = db.proj_dim;
        const int64_t rows = db.proj.data ? db.proj.rows : db.proj_f16.rows;
        const int64_t cols = db.proj.data ? db.proj.cols : db.proj_f16.cols;
        if (rows != (F + kFrameBlock - 1) / kFrameBlock || J < 2 || cols != kFrameBlock * J ||
            db.proj_basis.data == nullptr || db.proj_basis.rows != db.pose.cols ||
            db.proj_basis.cols != J - 1 || db.proj_mean.data == nullptr ||
            db.proj_mean.size != db.pose.cols || !(db.proj_max_norm >= 0.0) ||
            !(db.proj_max_norm < std::numeric_limits<double>::infinity())) {
            throw std::invalid_argument(
                "pose_proj: expected blocks (" + std::to_string((F + kFrameBlock - 1) / kFrameBlock) +
                ", 16 J) with J >= 2, basis (" + std::to_string(db.pose.cols) + ", J - 1), mean (" +
                std::to_string(db.pose.cols) + ",) and a finite max norm; got blocks (" +
                std::to_string(rows) + ", " + std::to_string(cols) + "), J = " + std::to_string(J));
        }
    }
    for (int64_t m = 0; m < db.seg_start.size; ++m) {
        const int64_t s = db.seg_start[m], L = db.seg_len[m];
        if (s < 0 || L < 0 || s > F || L > F - s) {
            throw std::invalid_argument("segment " + std::to_string(m) +
                                        ": expected [start, start+len) inside [0, " + std::to_string(F) +
                                        "); got start " + std::to_string(s) + ", len " + std::to_string(L));
        }
    }
}

}  // namespace gesturedb
