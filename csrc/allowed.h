// Which candidates a bitset allows (spec step 1): a candidate window is
// allowed iff its first and its last frame are set, so the filters, the exact
// pre-selection and the blocked batch walk the runs of allowed candidates of a
// segment through for_each_allowed_run, 64 candidates per pair of word reads.
#pragma once

#include <algorithm>
#include <cstdint>

#include "span.h"

namespace gesturedb {

// Bits f .. f+63 of a packed bitset (bits past the end read as 0).
inline uint64_t bits64(const BitsetView& b, int64_t f) {
    const int64_t w = f >> 6;
    const int sh = int(f & 63);
    const uint64_t lo = (w < b.n_words) ? b.words[w] : 0;
    if (sh == 0) return lo;
    const uint64_t hi = (w + 1 < b.n_words) ? b.words[w + 1] : 0;
    return (lo >> sh) | (hi << (64 - sh));
}

// Calls fn(i0, i1) for each maximal run [i0, i1) of candidates i in [0, count)
// whose window [first + i, first + i + last_off] has both its first and its last
// frame allowed (spec step 1: only those two frames are checked).
template <class Fn>
void for_each_allowed_run(const BitsetView& allowed, int64_t first, int64_t count, int64_t last_off,
                          Fn&& fn) {
    if (count <= 0) return;
    if (allowed.all()) {
        fn(int64_t(0), count);
        return;
    }
    int64_t run_start = -1;
    for (int64_t base = 0; base < count; base += 64) {
        const int64_t lim = std::min<int64_t>(64, count - base);
        uint64_t ok = bits64(allowed, first + base) & bits64(allowed, first + base + last_off);
        if (lim < 64) ok &= (uint64_t(1) << lim) - 1;
        int64_t i = 0;
        while (i < lim) {
            if (run_start < 0) {
                const uint64_t rest = ok >> i;
                if (rest == 0) break;
                i += __builtin_ctzll(rest);
                run_start = base + i;
            } else {
                const uint64_t rest = (~ok) >> i;
                if (rest == 0) break;  // the run continues into the next word
                i += __builtin_ctzll(rest);
                fn(run_start, base + i);
                run_start = -1;
            }
        }
    }
    if (run_start >= 0) fn(run_start, count);
}

}  // namespace gesturedb
