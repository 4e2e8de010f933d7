// Forward kinematics (fk.h).
#include "fk.h"

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

}  // namespace gesturedb
