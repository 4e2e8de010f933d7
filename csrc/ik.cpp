// Two-bone leg IK (ik.h). The steps and their order follow the numpy reference,
// gesturedb.synth.contacts._two_bone_ik_numpy, line for line; tests/test_placement.py
// checks the two agree to rounding (acos and sin here are libm's, not numpy's).
#include "ik.h"

#include <algorithm>
#include <cmath>

namespace gesturedb {

namespace {

struct V3 {
    double x, y, z;
};
struct Q {
    double w, x, y, z;
};

V3 sub(V3 a, V3 b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
V3 scale(V3 a, double s) { return {a.x * s, a.y * s, a.z * s}; }
double dot(V3 a, V3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
double norm(V3 a) { return std::sqrt(dot(a, a)); }
V3 cross(V3 a, V3 b) { return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x}; }
V3 unit(V3 v) { return scale(v, 1.0 / std::max(norm(v), 1e-12)); }
double clip1(double x) { return std::min(1.0, std::max(-1.0, x)); }
// the angle between two directions, in [0, pi]
double angle(V3 u, V3 v) { return std::acos(clip1(dot(unit(u), unit(v)))); }

// Hamilton product: first b, then a (gesturedb.rotations.multiply)
Q mul(Q a, Q b) {
    return {a.w * b.w - a.x * b.x - a.y * b.y - a.z * b.z, a.w * b.x + a.x * b.w + a.y * b.z - a.z * b.y,
            a.w * b.y - a.x * b.z + a.y * b.w + a.z * b.x, a.w * b.z + a.x * b.y - a.y * b.x + a.z * b.w};
}
// the conjugate over the squared norm (rotations.inverse): the inputs need not be exactly unit
Q inv(Q q) {
    const double s = q.w * q.w + q.x * q.x + q.y * q.y + q.z * q.z;
    return {q.w / s, -q.x / s, -q.y / s, -q.z / s};
}
// v rotated by the unit quaternion q: v + 2w (u x v) + 2 u x (u x v) (rotations.apply)
V3 apply(Q q, V3 v) {
    const V3 u{q.x, q.y, q.z};
    const V3 t = scale(cross(u, v), 2.0);
    const V3 c = cross(u, t);
    return {v.x + q.w * t.x + c.x, v.y + q.w * t.y + c.y, v.z + q.w * t.z + c.z};
}
// the rotation by `rad` about `axis` (any length; the unit direction is taken)
Q axis_angle(V3 axis, double rad) {
    const V3 r = scale(unit(axis), rad);
    const double half = 0.5 * norm(r);
    // sin(half) / |r|, which is 0.5 as the angle goes to 0 (rotations.from_axis_angle's sinc)
    const double s = half == 0.0 ? 0.5 : 0.5 * (std::sin(half) / half);
    return {std::cos(half), r.x * s, r.y * s, r.z * s};
}

Q load_q(const double* p) { return {p[0], p[1], p[2], p[3]}; }
V3 load_v(const double* p) { return {p[0], p[1], p[2]}; }
void store(double* p, Q q) { p[0] = q.w, p[1] = q.x, p[2] = q.y, p[3] = q.z; }

}  // namespace

void two_bone_ik(double* rot, const double* grot, const double* pos, const double* target, int64_t n,
                 int64_t J, int64_t hip, int64_t knee, int64_t ankle) {
    for (int64_t f = 0; f < n; ++f) {
        double* L = rot + f * J * 4;
        const double* G = grot + f * J * 4;
        const double* P = pos + f * J * 3;
        const V3 a = load_v(P + hip * 3), b = load_v(P + knee * 3), c = load_v(P + ankle * 3);
        const V3 t = load_v(target + f * 3);
        const double l_ab = norm(sub(b, a)), l_cb = norm(sub(b, c));
        // an unreachable target is approached as far as the leg reaches (never quite straight)
        const double l_at = std::min(std::max(norm(sub(t, a)), 1e-4), l_ab + l_cb - 1e-4);
        const double ac_ab_0 = angle(sub(c, a), sub(b, a));
        const double ba_bc_0 = angle(sub(a, b), sub(c, b));
        double ac_at_0 = angle(sub(c, a), sub(t, a));
        // the hip's and the knee's angles that make the hip-ankle distance l_at (law of cosines)
        const double ac_ab_1 =
            std::acos(clip1((l_cb * l_cb - l_ab * l_ab - l_at * l_at) / (-2 * l_ab * l_at)));
        const double ba_bc_1 =
            std::acos(clip1((l_at * l_at - l_ab * l_ab - l_cb * l_cb) / (-2 * l_ab * l_cb)));
        const Q g_hip = load_q(G + hip * 4), g_knee = load_q(G + knee * 4), g_ankle = load_q(G + ankle * 4);
        V3 axis0 = cross(sub(c, a), sub(b, a));
        // a straight leg has no bend plane: bend about the hip's own x axis (knees bend forward)
        if (norm(axis0) < 1e-8) axis0 = apply(g_hip, V3{1.0, 0.0, 0.0});
        V3 axis1 = cross(sub(c, a), sub(t, a));
        // the target on the hip-ankle line: no swing
        if (!(norm(axis1) > 1e-10)) axis1 = axis0, ac_at_0 = 0.0;
        const Q inv_a = inv(g_hip), inv_b = inv(g_knee);
        const Q r0 = axis_angle(apply(inv_a, axis0), ac_ab_1 - ac_ab_0);
        const Q r2 = axis_angle(apply(inv_a, axis1), ac_at_0);
        const Q r1 = axis_angle(apply(inv_b, axis0), ba_bc_1 - ba_bc_0);
        const Q l_hip = load_q(L + hip * 4), l_knee = load_q(L + knee * 4);
        // in world terms: bend in the leg's own plane first (r0), then swing the ankle onto the target (r2)
        const Q hip_new = mul(l_hip, mul(r2, r0));
        const Q knee_new = mul(l_knee, r1);
        // the knee's new world rotation = parent(hip) world * new hip local * new knee local
        const Q hip_parent = mul(g_hip, inv(l_hip));
        const Q knee_world = mul(mul(hip_parent, hip_new), knee_new);
        store(L + hip * 4, hip_new);
        store(L + knee * 4, knee_new);
        store(L + ankle * 4, mul(inv(knee_world), g_ankle));
    }
}

}  // namespace gesturedb
