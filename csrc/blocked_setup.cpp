// BlockedBatch's set-up (blocked.h): what it computes once per database and
// window length before the first step (the audio windows' norms, the rows'
// norms for the filter, the projection rows) and the error bounds that make
// its filter keep every candidate that could still win.
#include "blocked.h"
#include "pool.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace gesturedb {

BlockedBatch::BlockedBatch(const Kernels& kern, const Database& db, int64_t window, Preselect pre,
                           int threads, std::shared_ptr<const ProjRows> proj_rows)
    : kern_(kern), db_(db), N_(window), pre_(pre) {
    const int64_t F = db.n_frames(), Dp = db.pose.cols, Da = db.audio.cols;
    proj_ = pre == Preselect::Pose && db.has_proj();
    if (pre == Preselect::Pose) {
        // <a, a> of every N-frame audio window, for the audio distance of
        // the pre-selected candidates: cosdots_f32's own value (it does not
        // depend on the query), so the distances stay bit-identical
        const int64_t n_win = std::max<int64_t>(F - N_ + 1, 0);
        wnorm_.assign(std::max<int64_t>(n_win, 1), 0.0f);
        const int64_t chunk = 1 << 14;
        parallel_for((n_win + chunk - 1) / chunk, threads, [&](int64_t c, int) {
            const int64_t r0 = c * chunk, r1 = std::min(n_win, r0 + chunk);
            std::vector<float> zero(N_ * Da, 0.0f), qa(r1 - r0);
            kern_.cosdots_f32(db.audio.row(r0), r1 - r0, Da, N_ * Da, zero.data(), qa.data(), &wnorm_[r0]);
        });
    }
    if (proj_) {
        pr_ = proj_rows ? std::move(proj_rows) : build_proj_rows(db, threads);
        // segments with an unusable row among their candidates are scanned exactly
        const int64_t M = db.n_segments();
        seg_bad_.assign(std::max<int64_t>(M, 1), 0);
        for (int64_t m = 0; m < M; ++m) {
            const int64_t seg0 = db.seg_start[m], n_cand = db.seg_len[m] - N_;
            if (n_cand >= 1) seg_bad_[m] = pr_->n_bad[seg0 + n_cand] > pr_->n_bad[seg0];
        }
        return;
    }
    // per-row quantities of the filter (they only widen or narrow the
    // bound, never decide: any rounding here is covered by eps)
    const int64_t n_rows = pre == Preselect::Pose ? F : std::max<int64_t>(F - N_ + 1, 0);
    nrow_.assign(std::max<int64_t>(n_rows, 1), 0.0f);
    rrow_.assign(std::max<int64_t>(n_rows, 1), 0.0f);
    const int64_t chunk = 1 << 14;
    parallel_for((n_rows + chunk - 1) / chunk, threads, [&](int64_t c, int) {
        const int64_t r0 = c * chunk, r1 = std::min(n_rows, r0 + chunk);
        if (pre == Preselect::Pose) {
            const std::vector<float> zero(Dp, 0.0f);
            kern_.l2sq_rows_f32(db.pose.row(r0), r1 - r0, Dp, zero.data(), &nrow_[r0]);
            for (int64_t r = r0; r < r1; ++r) rrow_[r] = std::sqrt(nrow_[r]);
        } else {
            std::vector<float> zero(N_ * Da, 0.0f), qa(r1 - r0);
            kern_.cosdots_f32(db.audio.row(r0), r1 - r0, Da, N_ * Da, zero.data(), qa.data(), &nrow_[r0]);
            for (int64_t r = r0; r < r1; ++r) rrow_[r] = nrow_[r] > 0.0f ? 1.0f / std::sqrt(nrow_[r]) : 0.0f;
        }
    });
    // Error bound (see kernels.h): a float32 dot product of L terms is off
    // by at most gamma_L = L u / (1 - L u) times the sum of |terms|, u = 2^-24.
    // Pose: the filter's |row|^2 + |x|^2 - 2<row, x> and the exact kernel's
    // sum of squared differences each stay within ~gamma_{Dp+4} (|row| + |x|)^2
    // of the true distance; audio: both cosines within ~3 gamma_{n Da + 4}.
    // A factor 4 on top covers the rounding of the bound's own arithmetic.
    const double u = std::ldexp(1.0, -24);
    const int64_t L = pre == Preselect::Pose ? Dp : N_ * Da;
    const double gamma = double(L + 8) * u / (1.0 - double(L + 8) * u);
    eps_ = float(pre == Preselect::Pose ? 8.0 * gamma : 16.0 * gamma);
}

// ProjRows of db; a frame whose |z_f|^2 is not finite or above kProjBig
// (or whose residual is not finite) is marked unusable.
std::shared_ptr<const BlockedBatch::ProjRows> BlockedBatch::build_proj_rows(const Database& db, int threads) {
    const int64_t F = db.n_frames(), J = db.proj_dim;
    auto pr = std::make_shared<ProjRows>();
    pr->zrow.assign(size_t(std::max<int64_t>(F, 1)) * J, 0.0f);
    pr->pnrow.assign(std::max<int64_t>(F, 1), 0.0f);
    pr->rres.assign(std::max<int64_t>(F, 1), 0.0f);
    std::vector<uint8_t> bad(std::max<int64_t>(F, 1), 0);
    const int64_t chunk = 1 << 14;
    const int64_t n_chunks = (F + chunk - 1) / chunk;
    std::vector<double> zmax(std::max<int64_t>(n_chunks, 1), 0.0);
    parallel_for(n_chunks, threads, [&](int64_t c, int) {
        const int64_t f0 = c * chunk, f1 = std::min(F, f0 + chunk);
        for (int64_t f = f0; f < f1; ++f) {
            double s = 0.0;
            for (int64_t j = 0; j < J; ++j) {
                const float v = db.proj_value(f, j);
                pr->zrow[f * J + j] = v;
                s += double(v) * double(v);
            }
            pr->rres[f] = pr->zrow[f * J + J - 1];
            if (!(s <= kProjBig) || !std::isfinite(double(pr->rres[f]))) {
                bad[f] = 1;
                pr->pnrow[f] = 0.0f;
            } else {
                pr->pnrow[f] = float(s);
                zmax[c] = std::max(zmax[c], std::sqrt(s));
            }
        }
    });
    for (double z : zmax) pr->zmax = std::max(pr->zmax, z);
    pr->zmax *= 1.0 + 1e-6;  // and the rounding of the sums
    pr->n_bad.assign(F + 1, 0);
    for (int64_t f = 0; f < F; ++f) pr->n_bad[f + 1] = pr->n_bad[f] + bad[f];
    const double u = std::ldexp(1.0, -24);
    const double gamma = double(J + 8) * u / (1.0 - double(J + 8) * u);
    pr->eps = 4.0 * gamma;
    return pr;
}

// Harmless constants for lanes that do not filter (padding, exact lanes):
// their bits are never read, and every value stays finite.
void BlockedBatch::lane_defaults(std::vector<float>& par, int64_t qp) {
    std::fill(par.begin(), par.end(), 0.0f);
    std::fill(par.begin() + 1 * qp, par.begin() + 2 * qp, 1.0f);  // aup
    std::fill(par.begin() + 4 * qp, par.begin() + 5 * qp, 1.0f);  // alo
}

// The constants of lane l's bounds for the blocked form of the projection
// filter; false when they are not usable (the lane scans exactly).
//
// proj_filter bounds the exact float32 distance by a_lo Lh - c_lo and
// a_up Lh + b_up r_f + c_up, Lh being a float32 sum within gk of
// D = |z_f - z_x|^2 (z_f, z_x the stored float32 values). Here D comes as
// Dh = |z_f|^2 + |z_x|^2 - 2 <z_f, z_x> from a blocked float32 dot product:
// each term and the dot product are within gamma_{J+2} (|z_f| + |z_x|)^2
// of their real values, so |Dh - D| <= b = 4 gamma_{J+8} (Zmax + |z_x|)^2
// (twice that margin; Zmax >= every |z_f| the filter reads), one constant
// per lane. With D in [Dh - b, Dh + b]:
//   lower  a_lo Dh - (c_lo + 2 a_lo b)   <= a_lo D - c_lo  (also when Dh < 0,
//          where the extra a_lo b covers a_lo's rounding margin),
//   upper  a_up Dh + b_up r_f + (c_up + 2 a_up b) >= a_up D + b_up r_f + c_up,
// the constants rounded outwards, and the float evaluation of each (three
// roundings) is covered as in proj_query by a_lo's (1 - 8u), a_up's
// (1 + 4u) and the factor 2 on the b terms. No value can overflow: every
// |z|^2 in play is at most kProjBig and the largest upper bound is checked.
bool BlockedBatch::lane_bounds(const ProjQuery& pq, std::vector<float>& par, int64_t qp, int64_t l) const {
    if (!pq.ok) return false;
    const int64_t J = db_.proj_dim;
    double zx2 = 0.0;
    for (int64_t p = 0; p < J; ++p) zx2 += double(pq.zx[p]) * double(pq.zx[p]);
    if (!(zx2 <= kProjBig)) return false;
    const double u = std::ldexp(1.0, -24);
    const double zx = std::sqrt(zx2);
    const double zmax = pr_->zmax;
    const double b = pr_->eps * (zmax + zx) * (zmax + zx);
    const float inf = std::numeric_limits<float>::infinity();
    auto up = [&](double v) {
        float f = float(v);
        if (double(f) < v) f = std::nextafter(f, inf);
        return f;
    };
    const double aup = pq.a_up, alo = pq.a_lo;
    const float cup = up((double(pq.c_up) + 2.0 * aup * b) * (1.0 + 8.0 * u));
    const float clo = up((double(pq.c_lo) + 2.0 * alo * b) * (1.0 + 8.0 * u));
    // the largest value the upper bound can take (|Dh| <= (Zmax + |z_x|)^2 + b)
    const double ub_max = aup * ((zmax + zx) * (zmax + zx) + b) + double(pq.b_up) * zmax + cup;
    if (!(alo > 0.0) || !(aup > 0.0) || !(ub_max < 1e36) || !std::isfinite(double(clo))) return false;
    par[0 * qp + l] = float(zx2);
    par[1 * qp + l] = pq.a_up;
    par[2 * qp + l] = pq.b_up;
    par[3 * qp + l] = cup;
    par[4 * qp + l] = pq.a_lo;
    par[5 * qp + l] = clo;
    return true;
}

}  // namespace gesturedb
