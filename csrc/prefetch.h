// Prefetching of the scattered reads of a step: after the stream over the
// candidates, a step reads one row or window per segment at offsets only the
// pre-selection knows, and fetches them kScatterAhead segments ahead.
// benchmarks/floors.cpp reads its gather floor the same way, so it includes
// this header rather than a copy of the constant.
#pragma once

#include <cstdint>

namespace gesturedb {

inline void prefetch_bytes(const void* p, int64_t bytes) {
    const char* c = static_cast<const char*>(p);
    for (int64_t off = 0; off < bytes; off += 64) __builtin_prefetch(c + off);
}

// How many segments ahead a step's scattered passes prefetch (12 measured no
// faster, docs/scaling.md); the benchmark's gather floor uses the same.
constexpr int64_t kScatterAhead = 6;

}  // namespace gesturedb
