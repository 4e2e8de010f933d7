// The per-step arithmetic of the assembly that a live stream runs on a few frames at a
// time (gesturedb.synth.assemble): the placement of a piece, the pulls of the root
// towards the origin and +z, and the offset a seam starts. In numpy each was some forty array operations on
// arrays of a few elements per step, where the interpreter cost far more than the
// arithmetic; here they are plain scalar float64 loops, per frame and per joint, so
// the bits do not depend on how frames are split into calls (a live stream's and
// the offline synthesis's frames are the same).
#pragma once

#include <cstdint>

namespace gesturedb {

// The leaky integration of the root's turning and horizontal velocity
// (gesturedb.synth.assemble._Pull): for t in [first, T), with i = t - 1 + (1 - first),
//   h[t] = h[t-1] + dyaw[i] - kh * wrap(h[t-1]),
//   y[t] = y[t-1] + R(h[t] - yaw[t]) dx[i] - kp * y[t-1],
// where R(d) turns (x, z) about +y by d and wrap() is numpy's (a + pi) % 2pi - pi.
// h[first - 1] = h_prev and y[first - 1] = (y_prev0, y_prev1) come from before
// the block. yaw (T,), dyaw and dx (T - first,) and (T - first, 2); writes h (T,)
// and y (T, 2) from index first on. The same operations, in the same order, as the
// numpy loop it replaces (numpy's float64 remainder is fmod moved into the
// divisor's sign; its float64 sin and cos are libm's).
void pull_root(const double* yaw, const double* dyaw, const double* dx, int64_t T, int64_t first, double kh,
               double kp, double h_prev, double y_prev0, double y_prev1, double* h, double* y);

// A placement of frames (gesturedb.synth.assemble._place and placed_frames): for
// each of n frames, with q its quaternion (q: (n, 4), or (1, 4) for all) and s its
// source origin (src: (n, 3) or (1, 3)),
//   out_rot = rot with the root joint's rotation replaced by q * rot[:, 0],
//   out_root = rotate(q, root - s) (+ dst when given), its y kept from root,
// where zero_y zeroes the y of root - s before the rotation. rot, out_rot: (n, J, 4);
// root, out_root: (n, 3). The Hamilton product and the rotation of a vector
// (v + 2w (u x v) + u x 2(u x v)) are rotations.multiply's and rotations.apply's,
// every product and sum in the same order, so the bits are numpy's.
void place_frames(const double* q, bool q_per_frame, const double* rot, int64_t n, int64_t J,
                  const double* root, const double* src, bool src_per_frame, bool zero_y, const double* dst,
                  double* out_rot, double* out_root);

// The offset a seam starts (gesturedb.synth.assemble._seam_offset's arithmetic).
// old_rot, new_rot: (3, J, 4) the old motion's continuation and the new piece over
// the seam's first three frames; old_root, new_root: (3, 3). Per joint, the
// rotation vectors of old * new^-1 (angle in [0, pi]), each sample on the branch
// nearest the one before (seams.continuous_rotation_vectors), then value,
// velocity and acceleration at the seam by one-sided second-order differences
// (seams.seam_derivatives); the same for the root's position difference. With
// accel_rot (J,) and accel_root (have_accel), each decay is
// seams.adaptive_decays' (at least decay_s, long enough to stay within the
// typical acceleration), capped at max_decay_s; without, decay_s.
// Writes rot_der (3, J, 3): x0, v0, a0; root_der (3, 3); decay_rot (J,);
// *decay_root. atan2 here is libm's: numpy's float64 arctan2 rounds differently
// in the last bit for about 7 % of values (measured on an AVX-512 machine);
// tests/test_placement.py holds the two to rounding.
void seam_offset(const double* old_rot, const double* new_rot, const double* old_root, const double* new_root,
                 int64_t J, double fps, bool have_accel, const double* accel_rot, double accel_root,
                 double decay_s, double max_decay_s, double* rot_der, double* root_der, double* decay_rot,
                 double* decay_root);

}  // namespace gesturedb
