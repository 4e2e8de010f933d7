// Forward kinematics (fk.h).
#include "fk.h"

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <vector>

namespace gesturedb {

void forward_kinematics(const double* mats, const double* root, const int64_t* parents, const double* offsets,
                        int64_t F, int64_t J, double* pos, double* worlds) {
    // one frame's world matrices, when the caller does not keep them
    std::vector<double> scratch(worlds ? 0 : std::size_t(J) * 9);
    for (int64_t f = 0; f < F; ++f) {
        const double* L = mats + f * J * 9;
        double* P = pos + f * J * 3;
        double* W = worlds ? worlds + f * J * 9 : scratch.data();
        for (int k = 0; k < 3; ++k) P[k] = root[f * 3 + k];
        for (int k = 0; k < 9; ++k) W[k] = L[k];
        for (int64_t j = 1; j < J; ++j) {
            const double* Wp = W + parents[j] * 9;
            const double* Pp = P + parents[j] * 3;
            const double* o = offsets + j * 3;
            const double* Lj = L + j * 9;
            double* Wj = W + j * 9;
            for (int r = 0; r < 3; ++r) {
                P[j * 3 + r] = Pp[r] + (Wp[r * 3] * o[0] + Wp[r * 3 + 1] * o[1] + Wp[r * 3 + 2] * o[2]);
                for (int c = 0; c < 3; ++c)
                    Wj[r * 3 + c] = Wp[r * 3] * Lj[c] + Wp[r * 3 + 1] * Lj[3 + c] + Wp[r * 3 + 2] * Lj[6 + c];
            }
        }
    }
}

namespace {

// sqrt(w^2 + x^2 + y^2 + z^2), summed left to right as rotations._norm4 does
double norm4(const double* q) { return std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]); }

// rotations.to_matrix of one quaternion: m (3, 3) row-major
void quat_to_matrix(const double* q_in, double* m) {
    const double n = norm4(q_in);
    const double w = q_in[0] / n, x = q_in[1] / n, y = q_in[2] / n, z = q_in[3] / n;
    const double xx = x * x, yy = y * y, zz = z * z;
    const double xy = x * y, xz = x * z, yz = y * z;
    const double wx = w * x, wy = w * y, wz = w * z;
    m[0] = 1 - 2 * (yy + zz), m[1] = 2 * (xy - wz), m[2] = 2 * (xz + wy);
    m[3] = 2 * (xy + wz), m[4] = 1 - 2 * (xx + zz), m[5] = 2 * (yz - wx);
    m[6] = 2 * (xz - wy), m[7] = 2 * (yz + wx), m[8] = 1 - 2 * (xx + yy);
}

// rotations.from_matrix of one matrix (Shepperd's method): each branch divides by the largest
// of |w|, |x|, |y|, |z|, picked by the largest of the trace and the diagonal (the first on ties,
// as numpy's argmax); then normalised, w >= 0
void matrix_to_quat(const double* a, double* q) {
    const double cand[4] = {a[0] + a[4] + a[8], a[0], a[4], a[8]};
    int c = 0;
    for (int i = 1; i < 4; ++i)
        if (std::isnan(cand[c]) ? false : (std::isnan(cand[i]) || cand[i] > cand[c])) c = i;
    double v[4], t;
    switch (c) {
        case 0:
            t = std::sqrt(std::max(1 + a[0] + a[4] + a[8], 0.0));
            v[0] = 0.5 * t, v[1] = (a[7] - a[5]) / (2 * t), v[2] = (a[2] - a[6]) / (2 * t),
            v[3] = (a[3] - a[1]) / (2 * t);
            break;
        case 1:
            t = std::sqrt(std::max(1 + a[0] - a[4] - a[8], 0.0));
            v[0] = (a[7] - a[5]) / (2 * t), v[1] = 0.5 * t, v[2] = (a[1] + a[3]) / (2 * t),
            v[3] = (a[2] + a[6]) / (2 * t);
            break;
        case 2:
            t = std::sqrt(std::max(1 - a[0] + a[4] - a[8], 0.0));
            v[0] = (a[2] - a[6]) / (2 * t), v[1] = (a[1] + a[3]) / (2 * t), v[2] = 0.5 * t,
            v[3] = (a[5] + a[7]) / (2 * t);
            break;
        default:
            t = std::sqrt(std::max(1 - a[0] - a[4] + a[8], 0.0));
            v[0] = (a[3] - a[1]) / (2 * t), v[1] = (a[2] + a[6]) / (2 * t), v[2] = (a[5] + a[7]) / (2 * t),
            v[3] = 0.5 * t;
            break;
    }
    const double n = norm4(v);
    // np.where(w < 0, -q, q) after the division
    const double s = v[0] / n < 0.0 ? -1.0 : 1.0;
    for (int k = 0; k < 4; ++k) q[k] = s * (v[k] / n);
}

}  // namespace

void forward_kinematics_quat(const double* quats, const double* root, const int64_t* parents,
                             const double* offsets, int64_t F, int64_t J, double* pos, double* grot) {
    // one frame's local and world matrices at a time: the chain above, frame by frame
    std::vector<double> mats(std::size_t(J) * 9), worlds(std::size_t(J) * 9);
    for (int64_t f = 0; f < F; ++f) {
        for (int64_t j = 0; j < J; ++j) quat_to_matrix(quats + (f * J + j) * 4, mats.data() + j * 9);
        forward_kinematics(mats.data(), root + f * 3, parents, offsets, 1, J, pos + f * J * 3,
                           grot ? worlds.data() : nullptr);
        if (grot)
            for (int64_t j = 0; j < J; ++j) matrix_to_quat(worlds.data() + j * 9, grot + (f * J + j) * 4);
    }
}

}  // namespace gesturedb
