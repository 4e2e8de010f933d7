// Scalar kernels: the reference every SIMD kernel is checked against.
//
// The exact kernels (l2sq_rows, cosdots) spell out the summation order of
// kernels.h lane by lane, so that every ISA gives the same bits (they used to
// accumulate in double, closer to the float64 reference but not to the SIMD
// paths, and a search then depended on the CPU it ran on). std::fmaf is the
// one-rounding FMA of the SIMD paths: the FMA instruction where the CPU has
// one (glibc's ifunc), a correctly rounded software version elsewhere.
// The filters below keep float64 or plain loops: only bounds depend on them.
#include "kernels.h"

#include <cmath>
#include <cstring>
#include <limits>

namespace gesturedb {

namespace {

constexpr int kLanes = 16;

// Lanes A and B of kernels.h for a sum over len terms x_j y_j; x(j), y(j) give the factors.
template <class X, class Y>
inline void canonical_lanes(int64_t len, X x, Y y, float* A, float* B) {
    for (int l = 0; l < kLanes; ++l) A[l] = B[l] = 0.0f;
    int64_t j = 0;
    for (; j + 2 * kLanes <= len; j += 2 * kLanes)
        for (int l = 0; l < kLanes; ++l) {
            A[l] = std::fmaf(x(j + l), y(j + l), A[l]);
            B[l] = std::fmaf(x(j + kLanes + l), y(j + kLanes + l), B[l]);
        }
    if (j + kLanes <= len) {
        for (int l = 0; l < kLanes; ++l) A[l] = std::fmaf(x(j + l), y(j + l), A[l]);
        j += kLanes;
    }
    if (j < len)
        for (int l = 0; l < kLanes; ++l)
            B[l] = j + l < len ? std::fmaf(x(j + l), y(j + l), B[l]) : std::fmaf(0.0f, 0.0f, B[l]);
}

// A + B, then the tree (i, i+8), (i, i+4), (i, i+2), (i, i+1).
inline float canonical_total(const float* A, const float* B) {
    float s[kLanes];
    for (int l = 0; l < kLanes; ++l) s[l] = A[l] + B[l];
    for (int half = kLanes / 2; half >= 1; half /= 2)
        for (int i = 0; i < half; ++i) s[i] = s[i] + s[i + half];
    return s[0];
}

}  // namespace

void l2sq_rows_f32_scalar(const float* rows, int64_t n_rows, int64_t dim, const float* v, float* out) {
    float A[kLanes], B[kLanes];
    for (int64_t r = 0; r < n_rows; ++r) {
        const float* row = rows + r * dim;
        const auto d = [&](int64_t j) { return row[j] - v[j]; };
        canonical_lanes(dim, d, d, A, B);
        out[r] = canonical_total(A, B);
    }
}

void cosdots_f32_scalar(const float* base, int64_t n_win, int64_t stride, int64_t len, const float* q,
                        float* qa, float* aa) {
    float A[kLanes], B[kLanes];
    for (int64_t w = 0; w < n_win; ++w) {
        const float* a = base + w * stride;
        const auto qj = [&](int64_t j) { return q[j]; };
        const auto aj = [&](int64_t j) { return a[j]; };
        canonical_lanes(len, qj, aj, A, B);
        qa[w] = canonical_total(A, B);
        canonical_lanes(len, aj, aj, A, B);
        aa[w] = canonical_total(A, B);
    }
}

// --- batched-search filter --------------------------------------------------
// These are only ever a filter (see kernels.h), so float accumulation is fine;
// the scalar versions define the semantics the SIMD ones are tested against.

void dots_block_f32_scalar(const float* base, int64_t n_rows, int64_t stride, int64_t len, const float* xt,
                           int64_t qp, float* out) {
    const int64_t W = panel_width(qp);
    for (int64_t r = 0; r < n_rows; ++r) {
        const float* row = base + r * stride;
        float* o = out + r * qp;
        for (int64_t j = 0; j < qp; ++j) o[j] = 0.0f;
        for (int64_t p = 0; p < len; ++p) {
            const float b = row[p];
            for (int64_t j = 0; j < qp; ++j) o[j] += b * xt[(j / W) * len * W + p * W + j % W];
        }
    }
}

namespace {

// shared by both filters: d and b for lane j of row r are given by `dist`
template <class Dist>
void filter_scalar(int64_t n_rows, int64_t qp, const uint8_t* ok, float* minhi, uint64_t* keep, Dist dist) {
    const float inf = std::numeric_limits<float>::infinity();
    const float nan = std::numeric_limits<float>::quiet_NaN();
    for (int64_t r = 0; r < n_rows; ++r) {
        if (ok != nullptr && !ok[r]) continue;
        for (int64_t j = 0; j < qp; ++j) {
            float d, b;
            dist(r, j, d, b);
            const float hi = d + b;
            if (!(hi < inf) || minhi[j] != minhi[j]) {
                minhi[j] = nan;  // non-finite: the caller scans this query exactly
            } else if (hi < minhi[j]) {
                minhi[j] = hi;
            }
        }
    }
    const int64_t words = lane_words(qp);
    std::memset(keep, 0, sizeof(uint64_t) * size_t(n_rows * words));
    for (int64_t r = 0; r < n_rows; ++r) {
        if (ok != nullptr && !ok[r]) continue;
        for (int64_t j = 0; j < qp; ++j) {
            float d, b;
            dist(r, j, d, b);
            if (d - b <= minhi[j]) keep[r * words + j / 64] |= uint64_t(1) << (j % 64);
        }
    }
}

}  // namespace

void l2filter_f32_scalar(const float* c, int64_t n_rows, int64_t qp, const float* nrow, const float* rrow,
                         const uint8_t* ok, const float* nq, const float* rq, float eps, float* minhi,
                         uint64_t* keep) {
    filter_scalar(n_rows, qp, ok, minhi, keep, [&](int64_t r, int64_t j, float& d, float& b) {
        d = nrow[r] + nq[j] - 2.0f * c[r * qp + j];
        const float s = rrow[r] + rq[j];
        b = eps * (s * s);
    });
}

void cosfilter_f32_scalar(const float* c, int64_t n_rows, int64_t qp, const float* /*nrow*/,
                          const float* rrow, const uint8_t* ok, const float* /*nq*/, const float* rq,
                          float eps, float* minhi, uint64_t* keep) {
    filter_scalar(n_rows, qp, ok, minhi, keep, [&](int64_t r, int64_t j, float& d, float& b) {
        d = 1.0f - c[r * qp + j] * rrow[r] * rq[j];
        b = eps;
    });
}

// --- half-precision pose filter ----------------------------------------------

float half_to_float(uint16_t h) {
    const uint32_t sign = uint32_t(h & 0x8000u) << 16;
    const uint32_t exp = (h >> 10) & 0x1Fu;
    const uint32_t man = h & 0x3FFu;
    float f;
    if (exp == 0) {
        f = std::ldexp(float(man), -24);  // zero or subnormal: man * 2^-24
        return sign ? -f : f;
    }
    uint32_t bits;
    if (exp == 0x1F) bits = sign | 0x7F800000u | (man << 13);  // inf or NaN
    else bits = sign | ((exp + 112u) << 23) | (man << 13);
    std::memcpy(&f, &bits, sizeof f);
    return f;
}

void l2sq_rows_f16_scalar(const uint16_t* rows, int64_t n_rows, int64_t dim, const float* v, float* d) {
    for (int64_t r = 0; r < n_rows; ++r) {
        const uint16_t* row = rows + r * dim;
        double acc = 0.0;
        for (int64_t j = 0; j < dim; ++j) {
            const double e = double(half_to_float(row[j])) - double(v[j]);
            acc += e * e;
        }
        d[r] = float(acc);
    }
}

namespace {
inline double block_value(float x) { return double(x); }
inline double block_value(uint16_t h) { return double(half_to_float(h)); }

template <class T>
float l2sq_blocks_scalar(const T* blocks, int64_t f0, int64_t f1, int64_t dim, const float* v,
                         const float* up, float* out) {
    float umin = std::numeric_limits<float>::infinity();
    for (int64_t f = f0; f < f1; ++f) {
        const T* col = blocks + (f / kFrameBlock) * kFrameBlock * dim + f % kFrameBlock;
        double acc = 0.0;
        for (int64_t j = 0; j < dim; ++j) {
            const double e = block_value(col[j * kFrameBlock]) - double(v[j]);
            acc += e * e;
        }
        out[f - f0] = float(acc);
        if (up != nullptr) {
            const float rf = float(block_value(col[(dim - 1) * kFrameBlock]));
            const float ub = up[0] * out[f - f0] + up[1] * rf + up[2];
            umin = ub < umin ? ub : umin;  // a NaN fails the comparison
        }
    }
    return umin;
}
}  // namespace

float l2sq_blocks_f32_scalar(const float* blocks, int64_t f0, int64_t f1, int64_t dim, const float* v,
                             const float* up, float* out) {
    return l2sq_blocks_scalar(blocks, f0, f1, dim, v, up, out);
}

float l2sq_blocks_f16_scalar(const uint16_t* blocks, int64_t f0, int64_t f1, int64_t dim, const float* v,
                             const float* up, float* out) {
    return l2sq_blocks_scalar(blocks, f0, f1, dim, v, up, out);
}

// --- blocked batch: exact pairs and the projection filter -------------------

void l2sq_pairs_f32_scalar(const float* const* rows, const float* const* vs, int64_t n, int64_t dim,
                           float* out) {
    for (int64_t i = 0; i < n; ++i) l2sq_rows_f32_scalar(rows[i], 1, dim, vs[i], out + i);
}

void cosdots_pairs_f32_scalar(const float* const* wins, const float* const* qs, int64_t n, int64_t len,
                              float* qa) {
    for (int64_t i = 0; i < n; ++i) {
        float aa;
        cosdots_f32_scalar(wins[i], 1, 0, len, qs[i], qa + i, &aa);
    }
}

void projfilter_f32_scalar(const float* z, int64_t n_rows, int64_t J, const float* nrow, const float* rres,
                           const float* xt, int64_t qp, const ProjLanes& L, float* dh, float* umin) {
    const int64_t W = panel_width(qp);
    for (int64_t r = 0; r < n_rows; ++r) {
        const float* row = z + r * J;
        for (int64_t j = 0; j < qp; ++j) {
            const float* x = xt + (j / W) * J * W + j % W;
            double dot = 0.0;
            for (int64_t p = 0; p < J; ++p) dot += double(row[p]) * double(x[p * W]);
            const float d = (nrow[r] + L.nq[j]) - 2.0f * float(dot);
            dh[r * qp + j] = d;
            const float ub = L.aup[j] * d + (L.bup[j] * rres[r] + L.cup[j]);
            if (ub < umin[j]) umin[j] = ub;
        }
    }
}

void projkeep_f32_scalar(const float* dh, int64_t n_rows, int64_t qp, const ProjLanes& L, const float* umin,
                         uint64_t* keep) {
    const int64_t words = lane_words(qp);
    std::memset(keep, 0, sizeof(uint64_t) * size_t(n_rows * words));
    for (int64_t r = 0; r < n_rows; ++r)
        for (int64_t j = 0; j < qp; ++j)
            if (L.alo[j] * dh[r * qp + j] - L.clo[j] <= umin[j])
                keep[r * words + j / 64] |= uint64_t(1) << (j % 64);
}

}  // namespace gesturedb
