// A seam's rotation offsets applied to the frames after it
// (gesturedb.synth.seams.apply_quintic_rotation_offsets). Plain scalar float64
// per frame and joint: the numpy version (the quintic, the rotation vectors'
// quaternions, their products) ran some thirty small array operations per call,
// about 1 ms of a live step's apply in interpreter overhead.
#pragma once

#include <cstdint>

namespace gesturedb {

// x0, v0, a0: (J, 3) each joint's rotation-vector offset (rad), its velocity
// (rad/s) and acceleration (rad/s^2) at the seam; decay: (J,) seconds over which
// each decays to zero (> 0); t: (n,) seconds after the seam; rot: (n, J, 4) local
// rotations (w, x, y, z). Writes out (n, J, 4) = exp(offset(t)) * rot, where
// offset(t) is the quintic from (x0, v0, a0) at 0 to rest at decay, exactly 0
// from decay on. Every frame on its own: the bits do not depend on how frames
// are split into calls.
void apply_quintic_rotation_offsets(const double* x0, const double* v0, const double* a0, const double* decay,
                                    const double* t, int64_t n, int64_t J, const double* rot, double* out);

// base (n, k) + the quintic from (x0, v0, a0) (k,) at 0 to rest at decay (one
// decay for all k), at times t (n,): gesturedb.synth.seams.quintic_offsets added to
// a seam's root positions, the same operations in the same order.
void add_quintic_offsets(const double* x0, const double* v0, const double* a0, double decay, const double* t,
                         int64_t n, int64_t k, const double* base, double* out);

}  // namespace gesturedb
