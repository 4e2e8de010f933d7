// A seam's rotation offsets (seams.h). The arithmetic follows the numpy reference,
// gesturedb.synth.seams.quintic_offsets and apply_rotation_offsets, step for step;
// tests/test_placement.py checks the two agree to rounding (sin and cos here are
// libm's, not numpy's).
#include "seams.h"

#include <cmath>
#include <cstddef>
#include <vector>

namespace gesturedb {

void apply_quintic_rotation_offsets(const double* x0, const double* v0, const double* a0, const double* decay,
                                    const double* t, int64_t n, int64_t J, const double* rot, double* out) {
    // each joint's quintic: value, velocity and acceleration (x, v, a) at 0, all three 0 at D;
    // coefficients (A, B, C) per component, once per call
    std::vector<double> coef(std::size_t(J) * 9);
    for (int64_t j = 0; j < J; ++j) {
        const double D = decay[j];
        for (int k = 0; k < 3; ++k) {
            const double x = x0[j * 3 + k], v = v0[j * 3 + k], a = a0[j * 3 + k];
            double* c = &coef[std::size_t(j) * 9 + std::size_t(k) * 3];
            c[0] = -(a * D * D + 6 * v * D + 12 * x) / (2 * std::pow(D, 5));
            c[1] = (3 * a * D * D + 16 * v * D + 30 * x) / (2 * std::pow(D, 4));
            c[2] = -(3 * a * D * D + 12 * v * D + 20 * x) / (2 * std::pow(D, 3));
        }
    }
    for (int64_t i = 0; i < n; ++i) {
        const double ti = t[i];
        for (int64_t j = 0; j < J; ++j) {
            double off[3] = {0.0, 0.0, 0.0};
            if (ti < decay[j]) {  // from the decay on the offset is exactly 0 (the piece's own frame)
                for (int k = 0; k < 3; ++k) {
                    const double* c = &coef[std::size_t(j) * 9 + std::size_t(k) * 3];
                    off[k] =
                        ((((c[0] * ti + c[1]) * ti + c[2]) * ti + 0.5 * a0[j * 3 + k]) * ti + v0[j * 3 + k]) *
                            ti +
                        x0[j * 3 + k];
                }
            }
            // the offset's quaternion: (cos(angle/2), axis sin(angle/2)), sin(angle/2) / angle -> 0.5 at 0
            const double angle = std::sqrt(off[0] * off[0] + off[1] * off[1] + off[2] * off[2]);
            const double half = 0.5 * angle;
            const double s = angle == 0.0 ? 0.5 : std::sin(half) / angle;
            const double ow = std::cos(half), ox = off[0] * s, oy = off[1] * s, oz = off[2] * s;
            // Hamilton product offset * rot: the offset turns the joint after its own rotation
            const double* q = rot + (i * J + j) * 4;
            double* o = out + (i * J + j) * 4;
            o[0] = ow * q[0] - ox * q[1] - oy * q[2] - oz * q[3];
            o[1] = ow * q[1] + ox * q[0] + oy * q[3] - oz * q[2];
            o[2] = ow * q[2] - ox * q[3] + oy * q[0] + oz * q[1];
            o[3] = ow * q[3] + ox * q[2] - oy * q[1] + oz * q[0];
        }
    }
}

void add_quintic_offsets(const double* x0, const double* v0, const double* a0, double decay, const double* t,
                         int64_t n, int64_t k, const double* base, double* out) {
    const double D = decay;
    for (int64_t i = 0; i < n; ++i) {
        const double ti = t[i];
        for (int64_t c = 0; c < k; ++c) {
            const double x = x0[c], v = v0[c], a = a0[c];
            // quintic_offsets' A, B, C and Horner's scheme, operation for operation
            const double A = -(a * D * D + 6 * v * D + 12 * x) / (2 * std::pow(D, 5));
            const double B = (3 * a * D * D + 16 * v * D + 30 * x) / (2 * std::pow(D, 4));
            const double C = -(3 * a * D * D + 12 * v * D + 20 * x) / (2 * std::pow(D, 3));
            const double off = ti < D ? ((((A * ti + B) * ti + C) * ti + 0.5 * a) * ti + v) * ti + x : 0.0;
            out[i * k + c] = base[i * k + c] + off;
        }
    }
}

}  // namespace gesturedb
