// Orderings of distances: the comparisons, keys and sorts that decide ranks.
//
// The spec breaks every tie by the smaller index (segment, start), and a NaN
// distance must never break a sort, so the ranker and the shard merge order
// through these alone: nan_last_less for comparisons, order_key for radix keys
// (the same order as bits), radix_order for a stable full sort and
// select_smallest for a partial one.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <numeric>
#include <vector>

namespace gesturedb {

// Orders with NaN after every number (and NaNs equal to each other), so a
// non-finite feature can never break a sort's ordering; a NaN distance simply
// loses every comparison against a real one.
template <class T>
inline bool nan_last_less(T a, T b) {
    return a < b || (b != b && a == a);
}

// Order-preserving unsigned keys for the radix sort: -0 and +0 are equal (as
// they compare), every NaN sorts last and equal to the others, like nan_last_less.
inline uint32_t order_key(float x) {
    x += 0.0f;  // -0 -> +0
    if (x != x) return ~uint32_t(0);
    uint32_t u;
    std::memcpy(&u, &x, sizeof u);
    return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}
inline uint64_t order_key(double x) {
    x += 0.0;
    if (x != x) return ~uint64_t(0);
    uint64_t u;
    std::memcpy(&u, &x, sizeof u);
    return (u & 0x8000000000000000ull) ? ~u : (u | 0x8000000000000000ull);
}

// Stable LSD radix sort of the indices 0..K-1 by key: equal keys keep index
// order, which is exactly "ties broken by segment index" when the indices
// follow the segments. 11-bit digits; passes whose digit is the same for every
// key are skipped (the high digits of distances usually are).
template <class Key>
void radix_order(const Key* key, int32_t K, std::vector<int32_t>& ord, std::vector<int32_t>& tmp,
                 std::vector<uint32_t>& hist) {
    constexpr int kBits = 11;
    constexpr uint32_t kBuckets = 1u << kBits;
    constexpr int kPasses = int((8 * sizeof(Key) + kBits - 1) / kBits);
    ord.resize(K);
    tmp.resize(K);
    std::iota(ord.begin(), ord.end(), 0);
    if (K <= 1) return;
    hist.assign(size_t(kPasses) * kBuckets, 0);
    for (int32_t i = 0; i < K; ++i)
        for (int p = 0; p < kPasses; ++p) ++hist[p * kBuckets + ((key[i] >> (p * kBits)) & (kBuckets - 1))];
    for (int p = 0; p < kPasses; ++p) {
        uint32_t* h = &hist[p * kBuckets];
        if (h[(key[0] >> (p * kBits)) & (kBuckets - 1)] == uint32_t(K)) continue;
        uint32_t sum = 0;
        for (uint32_t b = 0; b < kBuckets; ++b) {
            const uint32_t c = h[b];
            h[b] = sum;
            sum += c;
        }
        for (int32_t i = 0; i < K; ++i) {
            const int32_t idx = ord[i];
            tmp[h[(key[idx] >> (p * kBits)) & (kBuckets - 1)]++] = idx;
        }
        ord.swap(tmp);
    }
}

// Moves the n smallest items of v (n < v.size(), unique under operator<) to
// its front, sorted. A radix pre-selection first: the keys of every item
// share the bits above the highest bit in which the smallest and the
// largest key differ, so the 11 bits below it order the items as their
// keys do; one histogram pass finds the digit of the n-th smallest, and
// only the items up to that digit (a few times n, typically) go through
// nth_element. hist: scratch.
template <class T, class KeyFn>
void select_smallest(std::vector<T>& v, int32_t n, KeyFn key, std::vector<uint32_t>& hist) {
    uint64_t lo = ~uint64_t(0), hi = 0;
    for (const T& x : v) {
        const uint64_t k = key(x);
        lo = k < lo ? k : lo;
        hi = k > hi ? k : hi;
    }
    const uint64_t diff = lo ^ hi;
    const int bits = diff ? 64 - __builtin_clzll(diff) : 0;
    const int shift = std::max(0, bits - 11);
    hist.assign(2048, 0);
    for (const T& x : v) ++hist[(key(x) >> shift) & 2047];
    uint32_t cum = 0, b = 0;
    for (; b < 2048; ++b) {
        cum += hist[b];
        if (cum >= uint32_t(n)) break;
    }
    const auto mid =
        std::partition(v.begin(), v.end(), [&](const T& x) { return ((key(x) >> shift) & 2047) <= b; });
    std::nth_element(v.begin(), v.begin() + (n - 1), mid);
    std::sort(v.begin(), v.begin() + n);
}

// Spec steps 4-5 over a Selection.
//
// Only the first k segments in (R, rp) order matter, and R = rp + ra >= L for
// every segment outside the L best by dp or outside the L best by da. So the
// ranker first ranks just those two top-L lists (a partial selection, O(K)):
// if the k-th of the segments in both lists has R < L, no other segment can

}  // namespace gesturedb
