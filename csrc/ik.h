// Analytic two-bone leg IK (gesturedb.synth.contacts.two_bone_ik). Plain scalar
// float64 per frame: the numpy version ran some eighty small array operations per
// call, and a live step calls it twice (once per planted leg), about 2.7 ms of
// interpreter overhead on a few frames' arithmetic.
#pragma once

#include <cstdint>

namespace gesturedb {

// rot: (n, J, 4) local rotations (w, x, y, z), updated in place at hip, knee and
// ankle; grot: (n, J, 4) their world rotations and pos: (n, J, 3) their world
// positions (metres), the forward kinematics of rot; target: (n, 3) where each
// frame's ankle should go (metres). Hip and knee turn so the ankle reaches the
// target (as far as the leg reaches); the ankle's local rotation changes so its
// world rotation stays. Every frame on its own: the bits do not depend on how
// frames are split into calls.
void two_bone_ik(double* rot, const double* grot, const double* pos, const double* target, int64_t n,
                 int64_t J, int64_t hip, int64_t knee, int64_t ankle);

}  // namespace gesturedb
