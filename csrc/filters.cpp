// The bounded filters of the pose pre-selection (filters.h), each with the
// derivation of its bound: why every candidate it drops is strictly worse, in
// the exact float32 distance, than one it keeps.
#include "filters.h"
#include "allowed.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>

namespace gesturedb {

// Pose pre-selection of segment m through the half-precision copy of pose.
//
// With h = binary16(p) (round to nearest), every element obeys
// |h - p| <= c1 |h| + c2 (c1 = 2^-11 / (1 - 2^-11) relative, c2 = 2^-25 absolute
// in the subnormal range), so ||h - p|| <= c1 ||h|| + c2 sqrt(Dp)
// <= c1 (||h - x|| + ||x||) + c2 sqrt(Dp). With eta = ||h - x|| and
// K = c1 ||x|| + c2 sqrt(Dp), the triangle inequality puts ||p - x|| in
// [(1 - c1) eta - K, (1 + c1) eta + K]. Both float32 sums (this filter's and the
// exact kernel's) are within a relative g of their real values. The candidate j
// with the smallest filtered distance dmin has an exact float32 distance of at
// most U = (1+g) ((1 + c1) sqrt(dmin / (1-g)) + K)^2; candidate i can only reach
// U, i.e. tie with or beat j, if its filtered distance is at most
// T = (1+g) ((sqrt(U / (1-g)) + K) / (1 - c1))^2. Those are kept (ascending);
// every other one is strictly worse than j in the exact float32 distance, so
// the exact minimum over the kept ones, ties to the smallest s, is the answer.
// The bound needs no norm of the rows, so the filter reads each half once.
// Appends the kept candidates to `kept`. Returns false when some value is not
// finite (an overflowing half, a NaN): the bound says nothing then and the
// caller scans the segment exactly.
bool half_filter(const Kernels& kern, const Database& db, int64_t m, const QueryStep& qs, double x_norm,
                 const BitsetView& allowed, float* dh, std::vector<int32_t>& kept) {
    const int64_t n_cand = db.seg_len[m] - qs.n;
    if (n_cand < 1) return true;
    const int64_t seg0 = db.seg_start[m], Dp = db.pose.cols;
    const float inf = std::numeric_limits<float>::infinity();
    float dmin = inf;
    int bad = 0;
    bool any = false;
    for_each_allowed_run(allowed, seg0 + 1, n_cand, qs.n - 1, [&](int64_t i0, int64_t i1) {
        any = true;
        kern.l2sq_rows_f16(db.pose_f16.row(seg0 + i0), i1 - i0, Dp, qs.prev, dh + i0);
        // branch-free so the compiler vectorises it (minps has these semantics)
        for (int64_t i = i0; i < i1; ++i) {
            const float d = dh[i];
            bad |= !(d < inf);
            dmin = d < dmin ? d : dmin;
        }
    });
    if (!any) return true;
    if (bad || !(x_norm < std::numeric_limits<double>::infinity())) return false;
    const double g = 2.0 * double(Dp + 4) * std::ldexp(1.0, -24);
    const double c1 = std::ldexp(1.0, -11) / (1.0 - std::ldexp(1.0, -11));
    const double c2 = std::ldexp(1.0, -25);
    const double K = c1 * x_norm * (1.0 + 1e-12) + c2 * std::sqrt(double(Dp));
    const double r = (1.0 + c1) * std::sqrt(double(dmin) / (1.0 - g)) + K;
    const double U = (1.0 + g) * r * r;
    const double t = (std::sqrt(U / (1.0 - g)) + K) / (1.0 - c1);
    const double T = (1.0 + g) * t * t * (1.0 + 1e-12);  // and the rounding of these lines
    // the float at or above T, so the test below can stay in float
    float Tf = float(T);
    if (double(Tf) < T) Tf = std::nextafter(Tf, inf);
    for_each_allowed_run(allowed, seg0 + 1, n_cand, qs.n - 1, [&](int64_t i0, int64_t i1) {
        for (int64_t i = i0; i < i1; ++i)
            if (dh[i] <= Tf) kept.push_back(int32_t(i));
    });
    return true;
}

ProjQuery proj_query(const Database& db, const float* x) {
    const int64_t Dp = db.pose.cols, J = db.proj_dim, k = J - 1;
    ProjQuery pq;
    pq.zx.assign(J, 0.0f);
    std::vector<double> d(Dp);
    double xn2 = 0.0;
    for (int64_t j = 0; j < Dp; ++j) {
        d[j] = double(x[j]) - db.proj_mean[j];
        xn2 += d[j] * d[j];
    }
    std::vector<double> c(k, 0.0);
    for (int64_t j = 0; j < Dp; ++j)
        for (int64_t i = 0; i < k; ++i) c[i] += d[j] * db.proj_basis(j, i);
    double r2 = 0.0;
    for (int64_t j = 0; j < Dp; ++j) {
        double e = d[j];
        for (int64_t i = 0; i < k; ++i) e -= db.proj_basis(j, i) * c[i];
        r2 += e * e;
    }
    for (int64_t i = 0; i < k; ++i) pq.zx[i] = float(c[i]);
    const double rx = std::sqrt(r2);
    pq.zx[k] = float(rx);
    // Error budget, u = 2^-24. The stored rows and this z_x are roundings of
    // float64 projections, so |z_f - z_x| (stored values) is within e0 of the
    // true |Z_f - Z_x|, and each stored r within e0 of the true one:
    //   float32 rows: e0 = 2^-21 S, S = max |P[f] - mean| + |x - mean| (|Z| =
    //     |p - mean|, so each rounding is at most 2^-24 |Z| per value, sqrt(J)
    //     2^-24 |Z| in norm; 2^-21 leaves room for J up to 64 and for the
    //     float64 projection);
    //   binary16 rows: plus 2^-11 (1 + 2^-10) max |P[f] - mean| + sqrt(J) 2^-25
    //     (relative rounding 2^-11 per value, 2^-25 absolute among subnormals,
    //     the 2^-10 for a float32 rounding on the way).
    // The filter's float32 sum Lh of J squares is within gk = 2 (J + 4) u of
    // |z_f - z_x|^2, the exact kernel's of Dp squares within g = 2 (Dp + 4) u of
    // the true distance, whatever the summation order. With eta (2^-12 for
    // float32 rows; 2^-9 for binary16, whose e0 is 2^10 larger: eta near
    // e0 / |z_f - z_x| at the distances that decide), (a -/+ e)^2 is >= / <=
    // (1 -/+ eta) a^2 -/+ (1/eta (+1)) e^2.
    const double u = std::ldexp(1.0, -24);
    const double S = db.proj_max_norm + std::sqrt(xn2);
    const bool half = db.proj_f16.data != nullptr;
    double e0 = std::ldexp(1.0, -21) * S * (1.0 + 1e-9);
    if (half)
        e0 += std::ldexp(1.0, -11) * (1.0 + std::ldexp(1.0, -10)) * db.proj_max_norm +
              std::sqrt(double(J)) * std::ldexp(1.0, -25);
    const double eta = std::ldexp(1.0, half ? -9 : -12);
    const double gk = 2.0 * double(J + 4) * u, g = 2.0 * double(Dp + 4) * u;
    const double tiny = double(Dp + J) * std::ldexp(1.0, -140);  // float underflow of the squares
    // exact d32 >= (1-g) ((1-eta) Lh / (1+gk) - e0^2 / eta); the per-row float
    // arithmetic of a_lo Lh - c_lo rounds by at most 2u, taken off a_lo
    pq.a_lo = float((1.0 - g) * (1.0 - eta) / (1.0 + gk) * (1.0 - 8.0 * u));
    pq.c_lo = float(((1.0 - g) * e0 * e0 / eta + tiny) * (1.0 + 8.0 * u));
    // exact d32 <= (1+g) ((1+eta) Lh / (1-gk) + (1 + 1/eta) e0^2 + 4 r_f r_x) with true r
    //          <= (1+g) ((1+eta) Lh / (1-gk) + 4 rf_stored (rx_stored + 2 e0) + (1 + 1/eta) e0^2
    //                    + 8 e0 (rx_stored + 2 e0))
    // (stored r values are within e0 of the true ones; 2 e0 leaves a margin)
    // rounded up by 8u for the float evaluation of a_up Lh + b_up r_f + c_up
    const double up = (1.0 + g) * (1.0 + 8.0 * u);
    const double rx2 = double(pq.zx[k]) + 2.0 * e0;
    pq.a_up = float(up * (1.0 + eta) / (1.0 - gk) * (1.0 + 4.0 * u));
    pq.b_up = float(up * 4.0 * rx2 * (1.0 + 4.0 * u));
    pq.c_up = float((up * ((1.0 + 1.0 / eta) * e0 * e0 + 8.0 * e0 * rx2) + tiny) * (1.0 + 4.0 * u));
    pq.ok = std::isfinite(S) && std::isfinite(double(pq.a_up)) && std::isfinite(double(pq.b_up)) &&
            std::isfinite(double(pq.c_up));
    return pq;
}

// Keeps the candidates whose lower bound can reach Umin, the smallest upper
// bound (filters.h).
bool proj_filter(const Kernels& kern, const Database& db, int64_t m, const QueryStep& qs, const ProjQuery& pq,
                 const BitsetView& allowed, float* dh, std::vector<int32_t>& kept) {
    const int64_t n_cand = db.seg_len[m] - qs.n;
    if (n_cand < 1) return true;
    if (!pq.ok) return false;
    const int64_t seg0 = db.seg_start[m], J = db.proj_dim;
    const float inf = std::numeric_limits<float>::infinity();
    float umin = inf;
    bool any = false;
    const float up[3] = {pq.a_up, pq.b_up, pq.c_up};
    for_each_allowed_run(allowed, seg0 + 1, n_cand, qs.n - 1, [&](int64_t i0, int64_t i1) {
        any = true;
        // candidate i's entry frame is seg0 + i
        // upper bounds a_up dh + b_up r_f + c_up, fused with the distances; a
        // NaN never lowers umin and is caught by the finiteness test on dh below
        const float u =
            db.proj.data != nullptr
                ? kern.l2sq_blocks_f32(db.proj.data, seg0 + i0, seg0 + i1, J, pq.zx.data(), up, dh + i0)
                : kern.l2sq_blocks_f16(db.proj_f16.data, seg0 + i0, seg0 + i1, J, pq.zx.data(), up, dh + i0);
        umin = u < umin ? u : umin;
    });
    if (!any) return true;
    if (!(umin < inf)) return false;
    bool bad = false;
    for_each_allowed_run(allowed, seg0 + 1, n_cand, qs.n - 1, [&](int64_t i0, int64_t i1) {
        // A segment keeps 1-3 of its ~56 candidates. One byte per candidate in a
        // loop the compiler vectorises, then eight flags per 64-bit load, most of
        // them zero: a loop carrying the kept count from candidate to candidate
        // was 9% of a one-thread step (perf).
        constexpr int64_t kBlock = 256;
        alignas(8) uint8_t flag[kBlock];
        uint8_t nonfinite = 0;
        for (int64_t b0 = i0; b0 < i1; b0 += kBlock) {
            const int64_t nb = std::min(kBlock, i1 - b0);
            const float* d = dh + b0;
            for (int64_t j = 0; j < nb; ++j) {
                flag[j] = uint8_t(pq.a_lo * d[j] - pq.c_lo <= umin);
                nonfinite |= uint8_t(!(d[j] < inf));
            }
            for (int64_t j = nb; j < ((nb + 7) & ~int64_t(7)); ++j) flag[j] = 0;
            for (int64_t j = 0; j < nb; j += 8) {
                uint64_t w;
                std::memcpy(&w, flag + j, 8);
                for (; w; w &= w - 1) kept.push_back(int32_t(b0 + j + (__builtin_ctzll(w) >> 3)));
            }
        }
        bad |= nonfinite != 0;
    });
    return !bad;
}

}  // namespace gesturedb
