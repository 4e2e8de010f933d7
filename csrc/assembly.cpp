// The assembly's per-step arithmetic (assembly.h). Each function follows its numpy
// reference operation for operation; the comments name the numpy expression a line
// reproduces where the order of operations is what keeps the bits.
#include "assembly.h"

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <vector>

namespace gesturedb {

namespace {

constexpr double kPi = 3.141592653589793;  // np.pi
constexpr double kTwoPi = 2 * kPi;         // 2 * np.pi, exact

// np.remainder(a, b) for float64: fmod, moved into b's sign (numpy's npy_divmod)
double np_remainder(double a, double b) {
    double mod = std::fmod(a, b);
    if (mod != 0.0) {
        if ((b < 0) != (mod < 0)) mod += b;
    } else {
        mod = std::copysign(0.0, b);
    }
    return mod;
}

// assemble._wrap: (a + pi) % (2 pi) - pi
double wrap(double a) { return np_remainder(a + kPi, kTwoPi) - kPi; }

// rotations.norm3: sqrt(x x + y y + z z), summed in order as numpy sums a last axis of 3
double norm3(const double* v) { return std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }

// rotations.to_axis_angle(rotations.multiply(a, rotations.inverse(b))) for one quaternion pair
void offset_vector(const double* a, const double* b, double* out) {
    // inverse: conjugate / sum(q * q) (the sum in order)
    const double n2 = b[0] * b[0] + b[1] * b[1] + b[2] * b[2] + b[3] * b[3];
    const double iw = b[0] / n2, ix = (b[1] * -1.0) / n2, iy = (b[2] * -1.0) / n2, iz = (b[3] * -1.0) / n2;
    // multiply(a, inverse(b))
    double q[4];
    q[0] = a[0] * iw - a[1] * ix - a[2] * iy - a[3] * iz;
    q[1] = a[0] * ix + a[1] * iw + a[2] * iz - a[3] * iy;
    q[2] = a[0] * iy - a[1] * iz + a[2] * iw + a[3] * ix;
    q[3] = a[0] * iz + a[1] * iy - a[2] * ix + a[3] * iw;
    // to_axis_angle: w >= 0 picks the angle in [0, pi]
    if (q[0] < 0.0)
        for (double& c : q) c = -c;
    const double s = norm3(q + 1);
    const double angle = 2.0 * std::atan2(s, q[0]);
    // angle / s -> 2 / w as s -> 0
    const double factor = s < 1e-12 ? 2.0 / q[0] : angle / s;
    for (int k = 0; k < 3; ++k) out[k] = q[1 + k] * factor;
}

// seams.seam_derivatives of three samples d0, d1, d2 (3 components each, stride apart)
void derivatives(const double* d0, const double* d1, const double* d2, double fps, double* x0, double* v0,
                 double* a0) {
    for (int k = 0; k < 3; ++k) {
        x0[k] = d0[k];
        v0[k] = (-3 * d0[k] + 4 * d1[k] - d2[k]) * (fps / 2);
        a0[k] = (d0[k] - 2 * d1[k] + d2[k]) * fps * fps;
    }
}

// seams.adaptive_decays for one offset, then np.minimum with the cap
double adaptive_decay(const double* x0, const double* v0, double accel, double decay_s, double max_decay_s) {
    const double x = norm3(x0), v = norm3(v0);
    const double a = std::max(accel, 1e-12);
    // np.maximum.reduce([decay_s, sqrt(10 / sqrt(3) * x / a), 15 / 8 * v / a])
    const double c = 10 / std::sqrt(3.0);
    double d = std::max(decay_s, std::sqrt(c * x / a));
    d = std::max(d, 15.0 / 8.0 * v / a);
    return std::min(d, max_decay_s);
}

}  // namespace

void place_frames(const double* q, bool q_per_frame, const double* rot, int64_t n, int64_t J,
                  const double* root, const double* src, bool src_per_frame, bool zero_y, const double* dst,
                  double* out_rot, double* out_root) {
    const std::size_t JJ = std::size_t(J);
    std::copy(rot, rot + std::size_t(n) * JJ * 4, out_rot);
    for (int64_t i = 0; i < n; ++i) {
        const double* a = q + (q_per_frame ? i * 4 : 0);
        const double *b = rot + std::size_t(i) * JJ * 4, *r = root + i * 3,
                     *o = src + (src_per_frame ? i * 3 : 0);
        double* p = out_rot + std::size_t(i) * JJ * 4;
        // rotations.multiply(q, root joint)
        p[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3];
        p[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2];
        p[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1];
        p[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0];
        // rotations.apply(q, v): t = 2 (u x v); v + w t + u x t
        double v[3] = {r[0] - o[0], r[1] - o[1], r[2] - o[2]};
        if (zero_y) v[1] = 0.0;
        const double w = a[0], u0 = a[1], u1 = a[2], u2 = a[3];
        const double t0 = 2.0 * (u1 * v[2] - u2 * v[1]);
        const double t1 = 2.0 * (u2 * v[0] - u0 * v[2]);
        const double t2 = 2.0 * (u0 * v[1] - u1 * v[0]);
        double out[3] = {v[0] + w * t0 + (u1 * t2 - u2 * t1), v[1] + w * t1 + (u2 * t0 - u0 * t2),
                         v[2] + w * t2 + (u0 * t1 - u1 * t0)};
        if (dst != nullptr)
            for (int c = 0; c < 3; ++c) out[c] += dst[c];
        out_root[i * 3] = out[0];
        out_root[i * 3 + 1] = r[1];  // the height is the source's
        out_root[i * 3 + 2] = out[2];
    }
}

void pull_root(const double* yaw, const double* dyaw, const double* dx, int64_t T, int64_t first, double kh,
               double kp, double h_prev, double y_prev0, double y_prev1, double* h, double* y) {
    for (int64_t t = first; t < T; ++t) {
        const int64_t i = t - 1 + (1 - first);  // frame t's difference
        h[t] = h_prev + dyaw[i] - kh * wrap(h_prev);
        const double delta = h[t] - yaw[t];
        const double c = std::cos(delta), s = std::sin(delta);
        // rotation about +y by delta: (x, z) -> (x cos + z sin, -x sin + z cos)
        const double v0 = c * dx[i * 2] + s * dx[i * 2 + 1];
        const double v1 = -s * dx[i * 2] + c * dx[i * 2 + 1];
        // y_prev + v - kp * y_prev
        y[t * 2] = y_prev0 + v0 - kp * y_prev0;
        y[t * 2 + 1] = y_prev1 + v1 - kp * y_prev1;
        h_prev = h[t];
        y_prev0 = y[t * 2];
        y_prev1 = y[t * 2 + 1];
    }
}

void seam_offset(const double* old_rot, const double* new_rot, const double* old_root, const double* new_root,
                 int64_t J, double fps, bool have_accel, const double* accel_rot, double accel_root,
                 double decay_s, double max_decay_s, double* rot_der, double* root_der, double* decay_rot,
                 double* decay_root) {
    const std::size_t JJ = std::size_t(J);
    std::vector<double> d(3 * JJ * 3);  // (3 samples, J, 3) rotation vectors
    for (int k = 0; k < 3; ++k)
        for (std::size_t j = 0; j < JJ; ++j)
            offset_vector(old_rot + (k * JJ + j) * 4, new_rot + (k * JJ + j) * 4, &d[(k * JJ + j) * 3]);
    // seams.continuous_rotation_vectors: sample k on the branch nearest sample k - 1
    for (std::size_t k = 1; k < 3; ++k)
        for (std::size_t j = 0; j < JJ; ++j) {
            double* cur = &d[(k * JJ + j) * 3];
            const double* prev = &d[((k - 1) * JJ + j) * 3];
            const double ang = std::max(norm3(cur), 1e-12);
            double other[3], to_other[3], to_cur[3];
            for (int c = 0; c < 3; ++c) {
                other[c] = cur[c] - kTwoPi * cur[c] / ang;  // d - 2 pi d / max(|d|, 1e-12)
                to_other[c] = other[c] - prev[c];
                to_cur[c] = cur[c] - prev[c];
            }
            if (norm3(to_other) < norm3(to_cur))
                for (int c = 0; c < 3; ++c) cur[c] = other[c];
        }
    for (std::size_t j = 0; j < JJ; ++j) {
        double* x0 = rot_der + j * 3;
        double* v0 = rot_der + (JJ + j) * 3;
        double* a0 = rot_der + (2 * JJ + j) * 3;
        derivatives(&d[j * 3], &d[(JJ + j) * 3], &d[(2 * JJ + j) * 3], fps, x0, v0, a0);
        decay_rot[j] = have_accel ? adaptive_decay(x0, v0, accel_rot[j], decay_s, max_decay_s) : decay_s;
    }
    double p[3][3];  // old_root - new_root
    for (int k = 0; k < 3; ++k)
        for (int c = 0; c < 3; ++c) p[k][c] = old_root[k * 3 + c] - new_root[k * 3 + c];
    derivatives(p[0], p[1], p[2], fps, root_der, root_der + 3, root_der + 6);
    *decay_root =
        have_accel ? adaptive_decay(root_der, root_der + 3, accel_root, decay_s, max_decay_s) : decay_s;
}

}  // namespace gesturedb
