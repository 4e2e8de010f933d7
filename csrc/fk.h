// Forward kinematics of a joint hierarchy over frames (Motion.positions and
// Motion.forward_kinematics). Plain scalar loops in float64: the numpy loop it
// replaces ran two small matrix products per joint, each a numpy call, which
// cost a live step more than the arithmetic (55 joints, 8 frames).
#pragma once

#include <cstdint>

namespace gesturedb {

// mats: (F, J, 3, 3) local rotation matrices (row-major, acting on column
// vectors); root: (F, 3); parents: (J,), parents[0] = -1 and parents[j] < j
// otherwise (parents first); offsets: (J, 3) rest offsets.
// Writes pos (F, J, 3): pos[j] = pos[parent] + W[parent] offsets[j], and, when
// worlds is not null, worlds (F, J, 3, 3): W[j] = W[parent] mats[j], W[0] = mats[0].
// Every frame on its own: the result does not depend on how frames are split.
void forward_kinematics(const double* mats, const double* root, const int64_t* parents, const double* offsets,
                        int64_t F, int64_t J, double* pos, double* worlds);

// The same from quaternions: quats (F, J, 4) local rotations (w, x, y, z; normalised first, so
// slightly off-unit input is fine); writes pos (F, J, 3) and, when grot is not null, the world
// rotations grot (F, J, 4) as unit quaternions with w >= 0. The conversions are those of
// gesturedb.rotations.to_matrix and from_matrix operation for operation (IEEE +, -, *, / and
// sqrt in the same order), so the result is numpy's to the bit: the numpy conversions cost a
// live step about 1 ms (two FKs of 8 frames) in call overhead.
void forward_kinematics_quat(const double* quats, const double* root, const int64_t* parents,
                             const double* offsets, int64_t F, int64_t J, double* pos, double* grot);

}  // namespace gesturedb
