// Rank-sum step, search loop and batch (spec: ../shared/spec/search.md).
//
// A step (spec steps 1-5) is split in three stages:
//   pre-selection  per segment, the allowed candidate with the smallest
//                  pose (or audio) distance and then its other distance;
//   ranking        ranks of the survivors by each distance (radix sort, ties by
//                  segment index), R = rp + ra, the k-th by (R, rp, m);
//   continuation   prev = P[g + n - 1] for the next step.
// The single-query path streams the database once per step. The batch runs many
// queries through the same stages and replaces the per-candidate distances of
// the pre-selection with a blocked dot product used as a bounded filter (see
// kernels.h), recomputing exactly every candidate that could still win; it
// therefore returns exactly what the single-query path returns.
#include "search.h"
#include "threads.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstring>
#include <exception>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <numeric>
#include <stdexcept>
#include <string>
#include <system_error>
#include <thread>

namespace gesturedb {
namespace {

// ---------------------------------------------------------------------------
// Threads: hnswlib's ParallelFor pattern. Tasks are handed out through an
// atomic counter; the first exception is kept, the other workers stop taking
// tasks, and it is rethrown on the calling thread after every worker joined.
template <class Fn>
void parallel_for(int64_t n_tasks, int threads, Fn&& fn) {
    if (n_tasks <= 0) return;
    threads = int(std::min<int64_t>(std::max(threads, 1), n_tasks));
    if (threads == 1) {
        for (int64_t i = 0; i < n_tasks; ++i) fn(i, 0);
        return;
    }
    std::atomic<int64_t> next{0};
    std::atomic<bool> stop{false};
    std::exception_ptr first;
    std::mutex first_mutex;
    auto worker = [&](int tid) {
        while (!stop.load(std::memory_order_relaxed)) {
            const int64_t i = next.fetch_add(1, std::memory_order_relaxed);
            if (i >= n_tasks) break;
            try {
                fn(i, tid);
            } catch (...) {
                std::lock_guard<std::mutex> lock(first_mutex);
                if (!first) first = std::current_exception();
                stop.store(true, std::memory_order_relaxed);
            }
        }
    };
    std::vector<std::thread> pool;
    pool.reserve(threads - 1);
    try {
        for (int t = 1; t < threads; ++t) pool.emplace_back(worker, t);
    } catch (const std::system_error&) {
        // the OS refused another thread: the ones that started (and this one)
        // still drain every task, only slower
    }
    worker(0);
    for (auto& th : pool) th.join();
    if (first) std::rethrow_exception(first);
}

// Orders with NaN after every number (and NaNs equal to each other), so a
// non-finite feature can never break a sort's ordering; a NaN distance simply
// loses every comparison against a real one.
template <class T>
inline bool nan_last_less(T a, T b) {
    return a < b || (b != b && a == a);
}

// Cosine distance from the float32 dot products, finished in double.
// Spec: da = 1 - <q,a> / (|q| |a|), and 1 when either norm is 0.
inline double cosine_distance(float qa, float qq, float aa) {
    if (qq == 0.0f || aa == 0.0f) return 1.0;
    return 1.0 - double(qa) / std::sqrt(double(qq) * double(aa));
}

// cosine_distance over arrays, written without branches so that the compiler
// vectorises the division and square root (both exactly rounded, so the values
// are those of cosine_distance).
void cosine_distances(const float* __restrict qa, const float* __restrict qq, const float* __restrict aa,
                      double* __restrict out, int64_t n) {
    for (int64_t i = 0; i < n; ++i) {
        const double q2 = qq[i], a2 = aa[i];
        const double den = std::sqrt(q2 * a2);
        const double d = 1.0 - double(qa[i]) / den;
        // 1 when either norm is 0, by masks: a ?: here is control flow to the vectoriser
        const uint64_t zero = -uint64_t((q2 == 0.0) | (a2 == 0.0));
        uint64_t bits, one_bits;
        const double one = 1.0;
        std::memcpy(&bits, &d, 8);
        std::memcpy(&one_bits, &one, 8);
        bits = (bits & ~zero) | (one_bits & zero);
        std::memcpy(&out[i], &bits, 8);
    }
}

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
void for_each_allowed_run(const BitsetView& allowed, int64_t first, int64_t count,
                          int64_t last_off, Fn&& fn) {
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

// Below this many values per step the thread start-up costs more than it saves.
constexpr int64_t kMinParallelWork = int64_t(1) << 17;

inline void prefetch_bytes(const void* p, int64_t bytes) {
    const char* c = static_cast<const char*>(p);
    for (int64_t off = 0; off < bytes; off += 64) __builtin_prefetch(c + off);
}

// Adds p[0..len) to 16 independent float partial sums (so the adds stay off
// the critical path and a loop is bound by memory) and the last len % 16 to
// tail: the read of the benchmark's floors.
inline void accumulate16(const float* p, int64_t len, float (&acc)[16], double& tail) {
    int64_t i = 0;
    for (; i + 16 <= len; i += 16)
        for (int j = 0; j < 16; ++j) acc[j] += p[i + j];
    for (; i < len; ++i) tail += p[i];
}

// How many segments ahead a step's scattered passes prefetch (12 measured no
// faster, docs/scaling.md); gather_sum_f32, their floor, uses the same.
constexpr int64_t kScatterAhead = 6;

}  // namespace

// ---------------------------------------------------------------------------
double stream_sum_f32(const float* data, int64_t n, int threads) {
    if (threads <= 0) threads = default_threads();
    // blocks of 1 MiB handed out dynamically, each summed by accumulate16
    constexpr int64_t block = int64_t(1) << 18;
    const int64_t n_blocks = (n + block - 1) / block;
    std::vector<double> partial(n_blocks, 0.0);
    parallel_for(n_blocks, threads, [&](int64_t b, int) {
        const float* p = data + b * block;
        const int64_t len = std::min(block, n - b * block);
        float acc[16] = {0};
        double s = 0.0;
        accumulate16(p, len, acc, s);
        for (int j = 0; j < 16; ++j) s += acc[j];
        partial[b] = s;
    });
    double s = 0.0;
    for (double x : partial) s += x;
    return s;
}

double gather_sum_f32(const float* data, int64_t rows, int64_t cols, const int64_t* starts, int64_t n,
                      int64_t rows_each, int threads) {
    if (threads <= 0) threads = default_threads();
    for (int64_t i = 0; i < n; ++i)
        if (starts[i] < 0 || starts[i] + rows_each > rows)
            throw std::invalid_argument("starts: row " + std::to_string(starts[i]) + " + " +
                                        std::to_string(rows_each) + " reaches outside the " +
                                        std::to_string(rows) + " rows");
    // chunks of starts handed out dynamically, each read with the step's
    // prefetch distance, as its scattered passes do
    constexpr int64_t chunk = 512;
    const int64_t n_chunks = (n + chunk - 1) / chunk, len = rows_each * cols;
    std::vector<double> partial(n_chunks, 0.0);
    parallel_for(n_chunks, threads, [&](int64_t c, int) {
        const int64_t i0 = c * chunk, i1 = std::min(n, i0 + chunk);
        auto prefetch = [&](int64_t i) { prefetch_bytes(data + starts[i] * cols, len * int64_t(sizeof(float))); };
        for (int64_t i = i0; i < std::min(i1, i0 + kScatterAhead); ++i) prefetch(i);
        float acc[16] = {0};
        double s = 0.0;
        for (int64_t i = i0; i < i1; ++i) {
            if (i + kScatterAhead < i1) prefetch(i + kScatterAhead);
            accumulate16(data + starts[i] * cols, len, acc, s);
        }
        for (int k = 0; k < 16; ++k) s += acc[k];
        partial[c] = s;
    });
    double s = 0.0;
    for (double x : partial) s += x;
    return s;
}

float Database::proj_value(int64_t f, int64_t j) const {
    const int64_t i = kFrameBlock * j + f % kFrameBlock;
    return proj.data != nullptr ? proj(f / kFrameBlock, i) : half_to_float(proj_f16(f / kFrameBlock, i));
}

void check_database(const Database& db) {
    const int64_t F = db.pose.rows;
    if (db.audio.rows != F) {
        throw std::invalid_argument("audio: expected " + std::to_string(F) +
                                    " rows like pose; got " + std::to_string(db.audio.rows));
    }
    if (db.pose.cols < 1 || db.audio.cols < 1) {
        throw std::invalid_argument("pose/audio: expected at least one feature column");
    }
    if (db.seg_len.size != db.seg_start.size) {
        throw std::invalid_argument("seg_len: expected " + std::to_string(db.seg_start.size) +
                                    " entries like seg_start; got " +
                                    std::to_string(db.seg_len.size));
    }
    if (F > int64_t(std::numeric_limits<int32_t>::max()) || db.seg_start.size > int64_t(std::numeric_limits<int32_t>::max())) {
        throw std::invalid_argument("database: expected fewer than 2^31 frames and segments");
    }
    if (db.pose_f16.data != nullptr && (db.pose_f16.rows != F || db.pose_f16.cols != db.pose.cols)) {
        throw std::invalid_argument("pose_f16: expected the shape of pose (" + std::to_string(F) + ", " +
                                    std::to_string(db.pose.cols) + "); got (" +
                                    std::to_string(db.pose_f16.rows) + ", " +
                                    std::to_string(db.pose_f16.cols) + ")");
    }
    if (db.proj.data != nullptr && db.proj_f16.data != nullptr)
        throw std::invalid_argument("pose_proj: expected float32 or binary16 blocks, not both");
    if (db.has_proj()) {
        const int64_t J = db.proj_dim;
        const int64_t rows = db.proj.data ? db.proj.rows : db.proj_f16.rows;
        const int64_t cols = db.proj.data ? db.proj.cols : db.proj_f16.cols;
        if (rows != (F + kFrameBlock - 1) / kFrameBlock || J < 2 || cols != kFrameBlock * J || db.proj_basis.data == nullptr || db.proj_basis.rows != db.pose.cols ||
            db.proj_basis.cols != J - 1 || db.proj_mean.data == nullptr || db.proj_mean.size != db.pose.cols ||
            !(db.proj_max_norm >= 0.0) || !(db.proj_max_norm < std::numeric_limits<double>::infinity())) {
            throw std::invalid_argument("pose_proj: expected blocks (" +
                                        std::to_string((F + kFrameBlock - 1) / kFrameBlock) +
                                        ", 16 J) with J >= 2, basis (" + std::to_string(db.pose.cols) +
                                        ", J - 1), mean (" + std::to_string(db.pose.cols) +
                                        ",) and a finite max norm; got blocks (" +
                                        std::to_string(rows) + ", " + std::to_string(cols) +
                                        "), J = " + std::to_string(J));
        }
    }
    for (int64_t m = 0; m < db.seg_start.size; ++m) {
        const int64_t s = db.seg_start[m], L = db.seg_len[m];
        if (s < 0 || L < 0 || s > F || L > F - s) {
            throw std::invalid_argument("segment " + std::to_string(m) + ": expected [start, start+len) inside [0, " +
                                        std::to_string(F) + "); got start " + std::to_string(s) +
                                        ", len " + std::to_string(L));
        }
    }
}

// ---------------------------------------------------------------------------
// Pre-selection results of one query at one step, indexed by segment.
struct Selection {
    int64_t* s;    // chosen offset, or -1 when the segment has no allowed candidate
    float* dp;     // its pose distance
    double* da;    // its audio distance
};

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
    const auto mid = std::partition(v.begin(), v.end(), [&](const T& x) { return ((key(x) >> shift) & 2047) <= b; });
    std::nth_element(v.begin(), v.begin() + (n - 1), mid);
    std::sort(v.begin(), v.begin() + n);
}

// Spec steps 4-5 over a Selection.
//
// Only the first k segments in (R, rp) order matter, and R = rp + ra >= L for
// every segment outside the L best by dp or outside the L best by da. So the
// ranker first ranks just those two top-L lists (a partial selection, O(K)):
// if the k-th of the segments in both lists has R < L, no other segment can
// come before it and the answer is exact. Otherwise (or when the last segment
// is asked for) it ranks everything with the radix sort. With independent
// ranks about L^2 / K segments land in both lists, so L = 256 almost always
// settles k <= 15 for K ~ 10^4 in a fraction of the full ranking's time.
class Ranker {
public:
    static constexpr int32_t kTop = 256;

    StepResult rank(const Database& db, const Selection& sel, int64_t n, int64_t k) {
        const int64_t M = db.n_segments();
        cand_.clear();
        for (int64_t m = 0; m < M; ++m)
            if (sel.s[m] >= 0) cand_.push_back(int32_t(m));
        StepResult r;
        const int32_t K = int32_t(cand_.size());
        r.n_candidates = K;
        if (K == 0) return r;
        // cand_ is in segment order, so ordering by (key, position) breaks ties by m
        kdp_.resize(K);
        kda_.resize(K);
        for (int32_t i = 0; i < K; ++i) {
            kdp_[i] = order_key(sel.dp[cand_[i]]);
            kda_[i] = order_key(sel.da[cand_[i]]);
        }
        int32_t c = -1;
        int64_t rp = 0, ra = 0;
        if (k < K && 2 * kTop < K && top_lists(K, k, c, rp, ra)) {
            // settled from the top lists
        } else {
            full(K, k, c, rp, ra);
        }
        const int64_t m = cand_[c];
        r.found = true;
        r.segment = m;
        r.start = sel.s[m];
        r.frame = db.seg_start[m] + sel.s[m];
        r.length = n;
        r.pose_dist = double(sel.dp[m]);
        r.audio_dist = sel.da[m];
        r.pose_rank = rp;
        r.audio_rank = ra;
        return r;
    }

private:
    bool top_lists(int32_t K, int64_t k, int32_t& c, int64_t& rp_out, int64_t& ra_out) {
        // (key, position) pairs are unique, so partial selection is exact
        pdp_.resize(K);
        pda_.resize(K);
        for (int32_t i = 0; i < K; ++i) {
            pdp_[i] = (uint64_t(kdp_[i]) << 32) | uint32_t(i);
            pda_[i] = {kda_[i], i};
        }
        select_smallest(pdp_, kTop, [](uint64_t x) { return x; }, hist_);
        select_smallest(pda_, kTop, [](const std::pair<uint64_t, int32_t>& x) { return x.first; }, hist_);
        rp_.assign(K, -1);
        for (int32_t r = 0; r < kTop; ++r) rp_[int32_t(pdp_[r] & 0xFFFFFFFFu)] = r;
        known_.clear();
        for (int32_t r = 0; r < kTop; ++r) {
            const int32_t i = pda_[r].second;
            if (rp_[i] >= 0) known_.push_back((uint64_t(uint32_t(rp_[i] + r)) << 32) | uint32_t(rp_[i]));
        }
        if (int64_t(known_.size()) < k) return false;
        std::nth_element(known_.begin(), known_.begin() + (k - 1), known_.end());
        const uint64_t key = known_[k - 1];
        if ((key >> 32) >= uint64_t(kTop)) return false;
        const int32_t rp = int32_t(key & 0xFFFFFFFFu);
        c = int32_t(pdp_[rp] & 0xFFFFFFFFu);
        rp_out = rp;
        ra_out = int64_t(key >> 32) - rp;
        return true;
    }

    void full(int32_t K, int64_t k, int32_t& c, int64_t& rp_out, int64_t& ra_out) {
        rp_.resize(K);
        ra_.resize(K);
        radix_order(kdp_.data(), K, ord_dp_, tmp_, hist_);
        for (int32_t i = 0; i < K; ++i) rp_[ord_dp_[i]] = i;
        radix_order(kda_.data(), K, ord_da_, tmp_, hist_);
        for (int32_t i = 0; i < K; ++i) ra_[ord_da_[i]] = i;
        // (R, rp) is unique (rp is a permutation), so it orders every candidate
        rkey_.resize(K);
        for (int32_t i = 0; i < K; ++i)
            rkey_[i] = (uint64_t(uint32_t(rp_[i] + ra_[i])) << 32) | uint32_t(rp_[i]);
        const int64_t kk = std::min<int64_t>(k, K) - 1;
        std::nth_element(rkey_.begin(), rkey_.begin() + kk, rkey_.end());
        c = ord_dp_[int32_t(rkey_[kk] & 0xFFFFFFFFu)];
        rp_out = rp_[c];
        ra_out = ra_[c];
    }

    std::vector<int32_t> cand_, ord_dp_, ord_da_, tmp_, rp_, ra_;
    std::vector<uint32_t> kdp_, hist_;
    std::vector<uint64_t> kda_, rkey_, pdp_, known_;
    std::vector<std::pair<uint64_t, int32_t>> pda_;
};

// One query's step inputs as the pre-selection sees them.
struct QueryStep {
    const float* prev;   // (Dp,)
    const float* q;      // (n * Da,)
    float qq;            // <q, q> from cosdots_f32, as every path computes it
    int64_t n;
};

inline float query_norm2(const Kernels& kern, const float* q, int64_t len) {
    float qa = 0.0f, qq = 0.0f;
    kern.cosdots_f32(q, 1, 0, len, q, &qa, &qq);
    return qq;
}

// Spec steps 1-3, first half: the allowed candidate of segment m with the
// smallest pre-selection distance, ties to the smallest s. scratch_a/b hold
// one value per candidate. Returns the candidate index i (s = i + 1) or -1 and
// writes the pre-selection distance into sel.
int64_t preselect_exact(const Kernels& kern, const Database& db, int64_t m, const QueryStep& qs,
                        Preselect pre, const BitsetView& allowed, float* scratch_a,
                        float* scratch_b, Selection& sel) {
    const int64_t n = qs.n;
    const int64_t n_cand = db.seg_len[m] - n;  // s = 1 .. seg_len - n
    if (n_cand < 1) return -1;
    const int64_t seg0 = db.seg_start[m];
    const int64_t Dp = db.pose.cols, Da = db.audio.cols;
    int64_t best = -1;
    if (pre == Preselect::Pose) {
        float best_dp = 0.0f;
        for_each_allowed_run(allowed, seg0 + 1, n_cand, n - 1, [&](int64_t i0, int64_t i1) {
            // the entry frame of candidate i is g - 1 = seg0 + i
            kern.l2sq_rows_f32(db.pose.row(seg0 + i0), i1 - i0, Dp, qs.prev, scratch_a);
            for (int64_t i = i0; i < i1; ++i) {
                const float d = scratch_a[i - i0];
                // strict: an equal distance later in the segment never wins
                if (best < 0 || nan_last_less(d, best_dp)) {
                    best = i;
                    best_dp = d;
                }
            }
        });
        if (best >= 0) sel.dp[m] = best_dp;
    } else {
        double best_da = 0.0;
        for_each_allowed_run(allowed, seg0 + 1, n_cand, n - 1, [&](int64_t i0, int64_t i1) {
            // the window of candidate i starts at g = seg0 + 1 + i
            kern.cosdots_f32(db.audio.row(seg0 + 1 + i0), i1 - i0, Da, n * Da, qs.q, scratch_a,
                             scratch_b);
            for (int64_t i = i0; i < i1; ++i) {
                const double d = cosine_distance(scratch_a[i - i0], qs.qq, scratch_b[i - i0]);
                if (best < 0 || nan_last_less(d, best_da)) {
                    best = i;
                    best_da = d;
                }
            }
        });
        if (best >= 0) sel.da[m] = best_da;
    }
    return best;
}

// Spec steps 1-3, second half: the other distance of the pre-selected candidate.
inline void complete_other(const Kernels& kern, const Database& db, int64_t m, const QueryStep& qs,
                           Preselect pre, Selection& sel) {
    const int64_t g = db.seg_start[m] + sel.s[m];
    if (pre == Preselect::Pose) {
        float qa = 0.0f, aa = 0.0f;
        kern.cosdots_f32(db.audio.row(g), 1, db.audio.cols, qs.n * db.audio.cols, qs.q, &qa, &aa);
        sel.da[m] = cosine_distance(qa, qs.qq, aa);
    } else {
        kern.l2sq_rows_f32(db.pose.row(g - 1), 1, db.pose.cols, qs.prev, &sel.dp[m]);
    }
}

// The rows complete_other will read for segment m: fetched ahead because the
// pre-selected candidates are scattered and each would otherwise be a cache miss.
inline void prefetch_other(const Database& db, int64_t m, const QueryStep& qs, Preselect pre,
                           const Selection& sel) {
    if (sel.s[m] < 0) return;
    const int64_t g = db.seg_start[m] + sel.s[m];
    if (pre == Preselect::Pose) prefetch_bytes(db.audio.row(g), qs.n * db.audio.cols * int64_t(sizeof(float)));
    else prefetch_bytes(db.pose.row(g - 1), db.pose.cols * int64_t(sizeof(float)));
}

// Pose pre-selection of segment m through the half-precision copy of pose.
//
// With h = binary16(p) (round to nearest), every element obeys
// |h - p| <= c1 |h| + c2 (c1 = 2^-11 / (1 - 2^-11) relative, c2 = 2^-25 absolute
// in the subnormal range), so ||h - p|| <= c1 ||h|| + c2 sqrt(Dp)
// <= c1 (||h - x|| + ||x||) + c2 sqrt(Dp). With eta = ||h - x|| and
// K = c1 ||x|| + c2 sqrt(Dp), the triangle inequality puts ||p - x|| in
// [(1 - c1) eta - K, (1 + c1) eta + K]. Both float32 sums (this filter's and the
// exact kernel's) are within a relative g of their real values. The candidate j
// with the smallest filtered distance dmin has an exact float32 distance of at
// most U = (1+g) ((1 + c1) sqrt(dmin / (1-g)) + K)^2; candidate i can only reach
// U, i.e. tie with or beat j, if its filtered distance is at most
// T = (1+g) ((sqrt(U / (1-g)) + K) / (1 - c1))^2. Those are kept (ascending);
// every other one is strictly worse than j in the exact float32 distance, so
// the exact minimum over the kept ones, ties to the smallest s, is the answer.
// The bound needs no norm of the rows, so the filter reads each half once.
// Appends the kept candidates to `kept`. Returns false when some value is not
// finite (an overflowing half, a NaN): the bound says nothing then and the
// caller scans the segment exactly.
bool half_filter(const Kernels& kern, const Database& db, int64_t m, const QueryStep& qs,
                 double x_norm, const BitsetView& allowed, float* dh, std::vector<int32_t>& kept) {
    const int64_t n_cand = db.seg_len[m] - qs.n;
    if (n_cand < 1) return true;
    const int64_t seg0 = db.seg_start[m], Dp = db.pose.cols;
    const float inf = std::numeric_limits<float>::infinity();
    float dmin = inf;
    int bad = 0;
    bool any = false;
    for_each_allowed_run(allowed, seg0 + 1, n_cand, qs.n - 1, [&](int64_t i0, int64_t i1) {
        any = true;
        kern.l2sq_rows_f16(db.pose_f16.row(seg0 + i0), i1 - i0, Dp, qs.prev, dh + i0);
        // branch-free so the compiler vectorises it (minps has these semantics)
        for (int64_t i = i0; i < i1; ++i) {
            const float d = dh[i];
            bad |= !(d < inf);
            dmin = d < dmin ? d : dmin;
        }
    });
    if (!any) return true;
    if (bad || !(x_norm < std::numeric_limits<double>::infinity())) return false;
    const double g = 2.0 * double(Dp + 4) * std::ldexp(1.0, -24);
    const double c1 = std::ldexp(1.0, -11) / (1.0 - std::ldexp(1.0, -11));
    const double c2 = std::ldexp(1.0, -25);
    const double K = c1 * x_norm * (1.0 + 1e-12) + c2 * std::sqrt(double(Dp));
    const double r = (1.0 + c1) * std::sqrt(double(dmin) / (1.0 - g)) + K;
    const double U = (1.0 + g) * r * r;
    const double t = (std::sqrt(U / (1.0 - g)) + K) / (1.0 - c1);
    const double T = (1.0 + g) * t * t * (1.0 + 1e-12);  // and the rounding of these lines
    // the float at or above T, so the test below can stay in float
    float Tf = float(T);
    if (double(Tf) < T) Tf = std::nextafter(Tf, inf);
    for_each_allowed_run(allowed, seg0 + 1, n_cand, qs.n - 1, [&](int64_t i0, int64_t i1) {
        for (int64_t i = i0; i < i1; ++i)
            if (dh[i] <= Tf) kept.push_back(int32_t(i));
    });
    return true;
}

// The query side of the projection filter: z_x = (U^T (x - mean), r_x) in
// double, its float32 copy for the filter kernel, and the constants of the
// bounds (see proj_filter).
struct ProjQuery {
    std::vector<float> zx;  // (J,)
    float a_lo = 0, c_lo = 0, a_up = 0, b_up = 0, c_up = 0;
    bool ok = false;        // false: not finite, every segment is scanned exactly
};

ProjQuery proj_query(const Database& db, const float* x) {
    const int64_t Dp = db.pose.cols, J = db.proj_dim, k = J - 1;
    ProjQuery pq;
    pq.zx.assign(J, 0.0f);
    std::vector<double> d(Dp);
    double xn2 = 0.0;
    for (int64_t j = 0; j < Dp; ++j) {
        d[j] = double(x[j]) - db.proj_mean[j];
        xn2 += d[j] * d[j];
    }
    std::vector<double> c(k, 0.0);
    for (int64_t j = 0; j < Dp; ++j)
        for (int64_t i = 0; i < k; ++i) c[i] += d[j] * db.proj_basis(j, i);
    double r2 = 0.0;
    for (int64_t j = 0; j < Dp; ++j) {
        double e = d[j];
        for (int64_t i = 0; i < k; ++i) e -= db.proj_basis(j, i) * c[i];
        r2 += e * e;
    }
    for (int64_t i = 0; i < k; ++i) pq.zx[i] = float(c[i]);
    const double rx = std::sqrt(r2);
    pq.zx[k] = float(rx);
    // Error budget, u = 2^-24. The stored rows and this z_x are roundings of
    // float64 projections, so |z_f - z_x| (stored values) is within e0 of the
    // true |Z_f - Z_x|, and each stored r within e0 of the true one:
    //   float32 rows: e0 = 2^-21 S, S = max |P[f] - mean| + |x - mean| (|Z| =
    //     |p - mean|, so each rounding is at most 2^-24 |Z| per value, sqrt(J)
    //     2^-24 |Z| in norm; 2^-21 leaves room for J up to 64 and for the
    //     float64 projection);
    //   binary16 rows: plus 2^-11 (1 + 2^-10) max |P[f] - mean| + sqrt(J) 2^-25
    //     (relative rounding 2^-11 per value, 2^-25 absolute among subnormals,
    //     the 2^-10 for a float32 rounding on the way).
    // The filter's float32 sum Lh of J squares is within gk = 2 (J + 4) u of
    // |z_f - z_x|^2, the exact kernel's of Dp squares within g = 2 (Dp + 4) u of
    // the true distance, whatever the summation order. With eta (2^-12 for
    // float32 rows; 2^-9 for binary16, whose e0 is 2^10 larger: eta near
    // e0 / |z_f - z_x| at the distances that decide), (a -/+ e)^2 is >= / <=
    // (1 -/+ eta) a^2 -/+ (1/eta (+1)) e^2.
    const double u = std::ldexp(1.0, -24);
    const double S = db.proj_max_norm + std::sqrt(xn2);
    const bool half = db.proj_f16.data != nullptr;
    double e0 = std::ldexp(1.0, -21) * S * (1.0 + 1e-9);
    if (half) e0 += std::ldexp(1.0, -11) * (1.0 + std::ldexp(1.0, -10)) * db.proj_max_norm +
                    std::sqrt(double(J)) * std::ldexp(1.0, -25);
    const double eta = std::ldexp(1.0, half ? -9 : -12);
    const double gk = 2.0 * double(J + 4) * u, g = 2.0 * double(Dp + 4) * u;
    const double tiny = double(Dp + J) * std::ldexp(1.0, -140);  // float underflow of the squares
    // exact d32 >= (1-g) ((1-eta) Lh / (1+gk) - e0^2 / eta); the per-row float
    // arithmetic of a_lo Lh - c_lo rounds by at most 2u, taken off a_lo
    pq.a_lo = float((1.0 - g) * (1.0 - eta) / (1.0 + gk) * (1.0 - 8.0 * u));
    pq.c_lo = float(((1.0 - g) * e0 * e0 / eta + tiny) * (1.0 + 8.0 * u));
    // exact d32 <= (1+g) ((1+eta) Lh / (1-gk) + (1 + 1/eta) e0^2 + 4 r_f r_x) with true r
    //          <= (1+g) ((1+eta) Lh / (1-gk) + 4 rf_stored (rx_stored + 2 e0) + (1 + 1/eta) e0^2
    //                    + 8 e0 (rx_stored + 2 e0))
    // (stored r values are within e0 of the true ones; 2 e0 leaves a margin)
    // rounded up by 8u for the float evaluation of a_up Lh + b_up r_f + c_up
    const double up = (1.0 + g) * (1.0 + 8.0 * u);
    const double rx2 = double(pq.zx[k]) + 2.0 * e0;
    pq.a_up = float(up * (1.0 + eta) / (1.0 - gk) * (1.0 + 4.0 * u));
    pq.b_up = float(up * 4.0 * rx2 * (1.0 + 4.0 * u));
    pq.c_up = float((up * ((1.0 + 1.0 / eta) * e0 * e0 + 8.0 * e0 * rx2) + tiny) * (1.0 + 4.0 * u));
    pq.ok = std::isfinite(S) && std::isfinite(double(pq.a_up)) && std::isfinite(double(pq.b_up)) &&
            std::isfinite(double(pq.c_up));
    return pq;
}

// Pose pre-selection filter of segment m through the projection (see
// Database::proj): the smallest upper bound Umin over the allowed candidates,
// then every candidate whose lower bound is <= Umin is kept (ascending). The
// exact minimum of the kept ones (ties to the smallest s) is the exact answer:
// the winner's exact distance is <= Umin and its lower bound <= that.
// Returns false when a value is not finite; the caller then scans exactly.
bool proj_filter(const Kernels& kern, const Database& db, int64_t m, const QueryStep& qs,
                 const ProjQuery& pq, const BitsetView& allowed, float* dh, std::vector<int32_t>& kept) {
    const int64_t n_cand = db.seg_len[m] - qs.n;
    if (n_cand < 1) return true;
    if (!pq.ok) return false;
    const int64_t seg0 = db.seg_start[m], J = db.proj_dim;
    const float inf = std::numeric_limits<float>::infinity();
    float umin = inf;
    bool any = false;
    const float up[3] = {pq.a_up, pq.b_up, pq.c_up};
    for_each_allowed_run(allowed, seg0 + 1, n_cand, qs.n - 1, [&](int64_t i0, int64_t i1) {
        any = true;
        // candidate i's entry frame is seg0 + i
        // upper bounds a_up dh + b_up r_f + c_up, fused with the distances; a
        // NaN never lowers umin and is caught by the finiteness test on dh below
        const float u = db.proj.data != nullptr
                            ? kern.l2sq_blocks_f32(db.proj.data, seg0 + i0, seg0 + i1, J, pq.zx.data(), up, dh + i0)
                            : kern.l2sq_blocks_f16(db.proj_f16.data, seg0 + i0, seg0 + i1, J, pq.zx.data(), up, dh + i0);
        umin = u < umin ? u : umin;
    });
    if (!any) return true;
    if (!(umin < inf)) return false;
    bool bad = false;
    for_each_allowed_run(allowed, seg0 + 1, n_cand, qs.n - 1, [&](int64_t i0, int64_t i1) {
        // A segment keeps 1-3 of its ~56 candidates. One byte per candidate in a
        // loop the compiler vectorises, then eight flags per 64-bit load, most of
        // them zero: a loop carrying the kept count from candidate to candidate
        // was 9% of a one-thread step (perf).
        constexpr int64_t kBlock = 256;
        alignas(8) uint8_t flag[kBlock];
        uint8_t nonfinite = 0;
        for (int64_t b0 = i0; b0 < i1; b0 += kBlock) {
            const int64_t nb = std::min(kBlock, i1 - b0);
            const float* d = dh + b0;
            for (int64_t j = 0; j < nb; ++j) {
                flag[j] = uint8_t(pq.a_lo * d[j] - pq.c_lo <= umin);
                nonfinite |= uint8_t(!(d[j] < inf));
            }
            for (int64_t j = nb; j < ((nb + 7) & ~int64_t(7)); ++j) flag[j] = 0;
            for (int64_t j = 0; j < nb; j += 8) {
                uint64_t w;
                std::memcpy(&w, flag + j, 8);
                for (; w; w &= w - 1) kept.push_back(int32_t(b0 + j + (__builtin_ctzll(w) >> 3)));
            }
        }
        bad |= nonfinite != 0;
    });
    return !bad;
}

// The exact pose pre-selection over the kept candidates [first, last) of half_filter.
int64_t argmin_kept(const Kernels& kern, const Database& db, int64_t m, const QueryStep& qs,
                    const int32_t* first, const int32_t* last, Selection& sel) {
    const int64_t seg0 = db.seg_start[m];
    int64_t best = -1;
    float best_dp = 0.0f;
    for (const int32_t* it = first; it != last; ++it) {
        float d;
        kern.l2sq_rows_f32(db.pose.row(seg0 + *it), 1, db.pose.cols, qs.prev, &d);
        if (best < 0 || nan_last_less(d, best_dp)) {
            best = *it;
            best_dp = d;
        }
    }
    if (best >= 0) sel.dp[m] = best_dp;
    return best;
}

// ---------------------------------------------------------------------------
struct StepEngine::Impl {
    const Kernels& kern;
    const Database& db;
    int threads;
    int64_t max_len = 0;
    std::vector<int64_t> chunk_begin;  // segment chunks of similar frame counts

    std::vector<int64_t> sel_s;
    std::vector<float> sel_dp;
    std::vector<double> sel_da;
    std::vector<std::vector<float>> scratch_a, scratch_b;  // per thread, one value per candidate
    // per thread: the half filter's kept candidates of a chunk, by segment
    std::vector<std::vector<int32_t>> kept_flat;
    std::vector<std::vector<int64_t>> kept_off;
    Ranker ranker;

    Impl(const Kernels& k, const Database& d, int t) : kern(k), db(d), threads(std::max(t, 1)) {
        const int64_t M = db.n_segments();
        for (int64_t m = 0; m < M; ++m) max_len = std::max(max_len, db.seg_len[m]);
        sel_s.assign(M, -1);
        sel_dp.assign(M, 0.0f);
        sel_da.assign(M, 0.0);
        scratch_a.assign(threads, std::vector<float>(std::max<int64_t>(max_len, 1)));
        scratch_b.assign(threads, std::vector<float>(std::max<int64_t>(max_len, 1)));
        kept_flat.assign(threads, {});
        kept_off.assign(threads, {});
        // about 8 chunks per thread so that dynamic scheduling evens out masks
        // that make some segments much cheaper than others
        int64_t total = 0;
        for (int64_t m = 0; m < M; ++m) total += db.seg_len[m];
        const int64_t n_chunks = threads > 1 ? int64_t(threads) * 8 : 1;
        const int64_t per_chunk = std::max<int64_t>(1, (total + n_chunks - 1) / n_chunks);
        chunk_begin.push_back(0);
        int64_t acc = 0;
        for (int64_t m = 0; m < M; ++m) {
            acc += db.seg_len[m];
            if (acc >= per_chunk && m + 1 < M) {
                chunk_begin.push_back(m + 1);
                acc = 0;
            }
        }
        chunk_begin.push_back(M);
    }

    StepResult step(const float* prev, const float* q, int64_t n, const StepOptions& opt) {
        return ranker.rank(db, preselect(prev, q, n, opt), n, opt.k);
    }

    // Spec steps 1-3 for every segment (sel_s = -1: no allowed candidate).
    Selection preselect(const float* prev, const float* q, int64_t n, const StepOptions& opt) {
        const QueryStep qs{prev, q, query_norm2(kern, q, n * db.audio.cols), n};
        Selection sel{sel_s.data(), sel_dp.data(), sel_da.data()};
        const int64_t n_chunks = int64_t(chunk_begin.size()) - 1;
        const int64_t work =
            db.n_frames() * (opt.preselect == Preselect::Pose ? db.pose.cols : 2 * n * db.audio.cols);
        const int use_threads = (threads > 1 && work >= kMinParallelWork) ? threads : 1;
        const bool proj = db.has_proj() && opt.preselect == Preselect::Pose;
        const bool half = !proj && db.pose_f16.data != nullptr && opt.preselect == Preselect::Pose;
        const bool filtered = half || proj;
        ProjQuery pq;
        if (proj) pq = proj_query(db, prev);
        double x_norm = 0.0;  // ||prev||, for the half filter's bound
        if (half) {
            for (int64_t j = 0; j < db.pose.cols; ++j) x_norm += double(prev[j]) * double(prev[j]);
            x_norm = std::sqrt(x_norm);
        }
        parallel_for(n_chunks, use_threads, [&](int64_t c, int tid) {
            const int64_t m0 = chunk_begin[c], m1 = chunk_begin[c + 1];
            float* sa = scratch_a[tid].data();
            float* sb = scratch_b[tid].data();
            // Pass 1 streams the chunk's candidates (exact pre-selection, or
            // with the half filter the few rows per segment that may win);
            // pass 2 reads those rows in float32, pass 3 the row or window of
            // each pre-selected candidate for its other distance. The scattered
            // reads of passes 2 and 3 are prefetched a few segments ahead.
            // (Measured: interleaving them with the stream instead, as a
            // software pipeline, made a 8.7 ms step 10.0 ms: they compete with
            // the stream for the line-fill buffers.)
            std::vector<int32_t>& kept = kept_flat[tid];
            std::vector<int64_t>& off = kept_off[tid];
            kept.clear();
            off.assign(m1 - m0 + 1, 0);
            for (int64_t m = m0; m < m1; ++m) {
                sel.s[m] = -1;
                off[m - m0] = int64_t(kept.size());
                if (opt.exclude != nullptr && opt.exclude[m]) continue;
                if (filtered) {
                    const size_t before = kept.size();
                    if (proj ? proj_filter(kern, db, m, qs, pq, opt.allowed, sa, kept)
                             : half_filter(kern, db, m, qs, x_norm, opt.allowed, sa, kept))
                        continue;
                    kept.resize(before);  // not finite: this segment is scanned exactly
                }
                const int64_t i = preselect_exact(kern, db, m, qs, opt.preselect, opt.allowed, sa, sb, sel);
                sel.s[m] = i < 0 ? -1 : i + 1;
            }
            off[m1 - m0] = int64_t(kept.size());
            if (filtered) {
                auto prefetch_kept = [&](int64_t m) {
                    for (int64_t j = off[m - m0]; j < off[m - m0 + 1]; ++j)
                        prefetch_bytes(db.pose.row(db.seg_start[m] + kept[j]), db.pose.cols * int64_t(sizeof(float)));
                };
                for (int64_t m = m0; m < std::min(m1, m0 + kScatterAhead); ++m) prefetch_kept(m);
                for (int64_t m = m0; m < m1; ++m) {
                    if (m + kScatterAhead < m1) prefetch_kept(m + kScatterAhead);
                    if (off[m - m0] == off[m - m0 + 1]) continue;  // scanned exactly or no candidate
                    const int64_t i = argmin_kept(kern, db, m, qs, kept.data() + off[m - m0],
                                                  kept.data() + off[m - m0 + 1], sel);
                    sel.s[m] = i < 0 ? -1 : i + 1;
                }
            }
            for (int64_t m = m0; m < std::min(m1, m0 + kScatterAhead); ++m) prefetch_other(db, m, qs, opt.preselect, sel);
            for (int64_t m = m0; m < m1; ++m) {
                if (m + kScatterAhead < m1) prefetch_other(db, m + kScatterAhead, qs, opt.preselect, sel);
                if (sel.s[m] >= 0) complete_other(kern, db, m, qs, opt.preselect, sel);
            }
        });
        return sel;
    }
};

StepEngine::StepEngine(const Kernels& kernels, const Database& db, int threads)
    : impl_(new Impl(kernels, db, threads)) {}
StepEngine::~StepEngine() = default;

StepResult StepEngine::step(const float* prev, const float* query, int64_t n,
                            const StepOptions& opt) {
    if (n < 1) throw std::invalid_argument("step: window length must be >= 1");
    return impl_->step(prev, query, n, opt);
}

TableRank rank_table(const int64_t* start, const float* pose_dist, const double* audio_dist, int64_t M,
                     int64_t k) {
    if (k < 1) throw std::invalid_argument("k: expected >= 1");
    if (M > int64_t(std::numeric_limits<int32_t>::max()))
        throw std::invalid_argument("table: expected fewer than 2^31 rows");
    // the ranker reads only the segment count and starts of a Database
    std::vector<int64_t> zero(std::max<int64_t>(M, 1), 0);
    Database db;
    db.seg_start = {zero.data(), M};
    db.seg_len = {zero.data(), M};
    // Selection is read-only here; the ranker never writes through it
    Selection sel{const_cast<int64_t*>(start), const_cast<float*>(pose_dist), const_cast<double*>(audio_dist)};
    Ranker ranker;
    const StepResult r = ranker.rank(db, sel, 0, k);
    TableRank out;
    out.n_candidates = r.n_candidates;
    if (r.found) {
        out.segment = r.segment;
        out.pose_rank = r.pose_rank;
        out.audio_rank = r.audio_rank;
    }
    return out;
}

void table_top_lists(const int64_t* start, const float* pose_dist, const double* audio_dist, int64_t Q,
                     int64_t M, int64_t n, int32_t* by_pose, int32_t* by_audio, int64_t* n_cand) {
    if (n < 1) throw std::invalid_argument("n: expected >= 1");
    if (M > int64_t(std::numeric_limits<int32_t>::max()))
        throw std::invalid_argument("table: expected fewer than 2^31 rows");
    // (key, row) pairs are unique and order as the ranker orders rows: ties by row index
    std::vector<uint64_t> p;
    std::vector<std::pair<uint64_t, int32_t>> a;
    std::vector<uint32_t> hist;
    for (int64_t q = 0; q < Q; ++q) {
        const int64_t* s = start + q * M;
        const float* dp = pose_dist + q * M;
        const double* da = audio_dist + q * M;
        // written in place: a pair built and then pushed back went through the stack, and
        // loading it whole after two smaller stores stalled every row (perf: 40% of the call)
        p.resize(M);
        a.resize(M);
        int64_t K = 0;
        for (int64_t m = 0; m < M; ++m) {
            if (s[m] < 0) continue;
            p[K] = (uint64_t(order_key(dp[m])) << 32) | uint32_t(m);
            a[K].first = order_key(da[m]);
            a[K].second = int32_t(m);
            ++K;
        }
        p.resize(K);
        a.resize(K);
        const int64_t take = std::min(n, K);
        if (take < K) {
            select_smallest(p, int32_t(take), [](uint64_t x) { return x; }, hist);
            select_smallest(a, int32_t(take), [](const std::pair<uint64_t, int32_t>& x) { return x.first; }, hist);
        } else {
            std::sort(p.begin(), p.end());
            std::sort(a.begin(), a.end());
        }
        int32_t* bp = by_pose + q * n;
        int32_t* ba = by_audio + q * n;
        for (int64_t r = 0; r < n; ++r) {
            bp[r] = r < take ? int32_t(p[r] & 0xFFFFFFFFu) : -1;
            ba[r] = r < take ? a[r].second : -1;
        }
        n_cand[q] = K;
    }
}

void StepEngine::preselect(const float* prev, const float* query, int64_t n, const StepOptions& opt,
                           int64_t* start, float* pose_dist, double* audio_dist) {
    if (n < 1) throw std::invalid_argument("step: window length must be >= 1");
    const Selection sel = impl_->preselect(prev, query, n, opt);
    const int64_t M = impl_->db.n_segments();
    std::copy(sel.s, sel.s + M, start);
    for (int64_t m = 0; m < M; ++m) {
        pose_dist[m] = sel.s[m] >= 0 ? sel.dp[m] : 0.0f;
        audio_dist[m] = sel.s[m] >= 0 ? sel.da[m] : 0.0;
    }
}

// ---------------------------------------------------------------------------
namespace {

void write_step(const SearchOutput& out, int64_t i, int64_t t, const StepResult& r) {
    out.segment[i] = r.segment;
    out.start[i] = r.start;
    out.frame[i] = r.frame;
    out.length[i] = r.length;
    out.out_frame[i] = t;
    out.pose_dist[i] = r.pose_dist;
    out.audio_dist[i] = r.audio_dist;
    out.pose_rank[i] = r.pose_rank;
    out.audio_rank[i] = r.audio_rank;
    out.n_candidates[i] = r.n_candidates;
}

int64_t n_steps(int64_t T, int64_t window) { return (T + window - 1) / window; }

int64_t run_search(StepEngine& engine, const Database& db, Span2<const float> query,
                   const float* init_pose, int64_t window, int64_t k, Preselect preselect,
                   const AllowedSchedule& allowed, const bool* exclude, const SearchOutput& out) {
    const int64_t T = query.rows;
    const float* prev = init_pose;
    StepOptions opt;
    opt.k = k;
    opt.preselect = preselect;
    opt.exclude = exclude;
    for (int64_t i = 0; i < n_steps(T, window); ++i) {
        const int64_t t = i * window;
        const int64_t n = std::min(window, T - t);  // the last window may be partial
        opt.allowed = allowed.at(i);
        const StepResult r = engine.step(prev, query.row(t), n, opt);
        if (!r.found) return i;
        write_step(out, i, t, r);
        // the next window continues from the last frame this one copies
        prev = db.pose.row(r.frame + n - 1);
    }
    return -1;
}

void check_search_args(const Database& db, Span2<const float> query, int64_t window, int64_t k,
                       const AllowedSchedule& allowed) {
    if (query.cols != db.audio.cols)
        throw std::invalid_argument("query: expected " + std::to_string(db.audio.cols) +
                                    " audio columns; got " + std::to_string(query.cols));
    if (query.rows < 1) throw std::invalid_argument("query: expected at least one frame");
    if (window < 1) throw std::invalid_argument("step: expected >= 1");
    if (k < 1) throw std::invalid_argument("k: expected >= 1");
    if (allowed.words != nullptr) {
        if (allowed.n_words != (db.n_frames() + 63) / 64)
            throw std::invalid_argument("allowed: wrong number of words");
        if (allowed.per_step && allowed.n_rows != n_steps(query.rows, window))
            throw std::invalid_argument("allowed: expected " + std::to_string(n_steps(query.rows, window)) +
                                        " rows (one per step); got " + std::to_string(allowed.n_rows));
    }
}

// ---------------------------------------------------------------------------
// Blocked batch: a block of queries advances step by step together. At each
// step the queries whose window is full (n = N) form the lanes of a panel; per
// segment one blocked dot product gives every lane's approximate distance to
// every candidate, the bound filter keeps the candidates that could still be
// the lane's minimum, and those are recomputed with the exact kernels in
// ascending s. Queries in their last, partial window take the single path.
//
// With a pose projection (Database::proj) and pose pre-selection, the blocked
// dot product runs over the J projected columns instead of the Dp pose columns
// (a quarter of the work at J = 24, Dp = 96) and the filter is the projection's
// bound of proj_filter, widened by the error of the blocked form (see
// lane_bounds): the same candidates-that-could-win are recomputed exactly, so
// the results stay those of the single path.
class BlockedBatch {
public:
    static constexpr int64_t kRowTile = 128;  // candidates per dot-product call
    // Projection filter: rows or lanes with |z|^2 above this take the exact scan,
    // so that no value of the blocked bound can overflow (see lane_bounds).
    static constexpr double kProjBig = 1e30;

    // The projection in the layout of the blocked dot product (rows of J
    // values), |z_f|^2 and r_f per frame. It does not depend on the window
    // length, so a BatchPlan builds it once for every window it serves.
    struct ProjRows {
        std::vector<float> zrow, pnrow, rres;
        std::vector<int64_t> n_bad;  // (F + 1,): frames before f whose row the filter cannot use
        double zmax = 0.0, eps = 0.0;
    };

    // proj_rows: the database's ProjRows when already built (null: built here).
    BlockedBatch(const Kernels& kern, const Database& db, int64_t window, Preselect pre, int threads,
                 std::shared_ptr<const ProjRows> proj_rows = nullptr)
        : kern_(kern), db_(db), N_(window), pre_(pre) {
        const int64_t F = db.n_frames(), Dp = db.pose.cols, Da = db.audio.cols;
        proj_ = pre == Preselect::Pose && db.has_proj();
        if (pre == Preselect::Pose) {
            // <a, a> of every N-frame audio window, for the audio distance of
            // the pre-selected candidates: cosdots_f32's own value (it does not
            // depend on the query), so the distances stay bit-identical
            const int64_t n_win = std::max<int64_t>(F - N_ + 1, 0);
            wnorm_.assign(std::max<int64_t>(n_win, 1), 0.0f);
            const int64_t chunk = 1 << 14;
            parallel_for((n_win + chunk - 1) / chunk, threads, [&](int64_t c, int) {
                const int64_t r0 = c * chunk, r1 = std::min(n_win, r0 + chunk);
                std::vector<float> zero(N_ * Da, 0.0f), qa(r1 - r0);
                kern_.cosdots_f32(db.audio.row(r0), r1 - r0, Da, N_ * Da, zero.data(), qa.data(), &wnorm_[r0]);
            });
        }
        if (proj_) {
            pr_ = proj_rows ? std::move(proj_rows) : build_proj_rows(db, threads);
            // segments with an unusable row among their candidates are scanned exactly
            const int64_t M = db.n_segments();
            seg_bad_.assign(std::max<int64_t>(M, 1), 0);
            for (int64_t m = 0; m < M; ++m) {
                const int64_t seg0 = db.seg_start[m], n_cand = db.seg_len[m] - N_;
                if (n_cand >= 1) seg_bad_[m] = pr_->n_bad[seg0 + n_cand] > pr_->n_bad[seg0];
            }
            return;
        }
        // per-row quantities of the filter (they only widen or narrow the
        // bound, never decide: any rounding here is covered by eps)
        const int64_t n_rows = pre == Preselect::Pose ? F : std::max<int64_t>(F - N_ + 1, 0);
        nrow_.assign(std::max<int64_t>(n_rows, 1), 0.0f);
        rrow_.assign(std::max<int64_t>(n_rows, 1), 0.0f);
        const int64_t chunk = 1 << 14;
        parallel_for((n_rows + chunk - 1) / chunk, threads, [&](int64_t c, int) {
            const int64_t r0 = c * chunk, r1 = std::min(n_rows, r0 + chunk);
            if (pre == Preselect::Pose) {
                const std::vector<float> zero(Dp, 0.0f);
                kern_.l2sq_rows_f32(db.pose.row(r0), r1 - r0, Dp, zero.data(), &nrow_[r0]);
                for (int64_t r = r0; r < r1; ++r) rrow_[r] = std::sqrt(nrow_[r]);
            } else {
                std::vector<float> zero(N_ * Da, 0.0f), qa(r1 - r0);
                kern_.cosdots_f32(db.audio.row(r0), r1 - r0, Da, N_ * Da, zero.data(), qa.data(), &nrow_[r0]);
                for (int64_t r = r0; r < r1; ++r) rrow_[r] = nrow_[r] > 0.0f ? 1.0f / std::sqrt(nrow_[r]) : 0.0f;
            }
        });
        // Error bound (see kernels.h): a float32 dot product of L terms is off
        // by at most gamma_L = L u / (1 - L u) times the sum of |terms|, u = 2^-24.
        // Pose: the filter's |row|^2 + |x|^2 - 2<row, x> and the exact kernel's
        // sum of squared differences each stay within ~gamma_{Dp+4} (|row| + |x|)^2
        // of the true distance; audio: both cosines within ~3 gamma_{n Da + 4}.
        // A factor 4 on top covers the rounding of the bound's own arithmetic.
        const double u = std::ldexp(1.0, -24);
        const int64_t L = pre == Preselect::Pose ? Dp : N_ * Da;
        const double gamma = double(L + 8) * u / (1.0 - double(L + 8) * u);
        eps_ = float(pre == Preselect::Pose ? 8.0 * gamma : 16.0 * gamma);
    }

    const std::shared_ptr<const ProjRows>& proj_rows() const { return pr_; }

    // Runs every query of the block through all its steps (allowed: the
    // bitset of each step).
    void run(BatchQuery* const* block, int64_t nq, const AllowedSchedule& allowed_steps) const {
        const int64_t M = db_.n_segments();
        const int64_t Dp = db_.pose.cols, Da = db_.audio.cols;
        const int64_t J = db_.proj_dim;
        const int64_t len = proj_ ? J : pre_ == Preselect::Pose ? Dp : N_ * Da;
        const int64_t qp = (nq + kQueryPanel - 1) / kQueryPanel * kQueryPanel;
        const int64_t words = qp / 64;
        std::vector<const float*> prev(nq);
        std::vector<int64_t> S(nq);
        int64_t max_steps = 0;
        for (int64_t i = 0; i < nq; ++i) {
            prev[i] = block[i]->init_pose;
            S[i] = n_steps(block[i]->audio.rows, N_);
            block[i]->failed_step = -1;
            max_steps = std::max(max_steps, S[i]);
        }
        std::vector<int64_t> sel_s(size_t(nq) * M);
        std::vector<float> sel_dp(size_t(nq) * M);
        std::vector<double> sel_da(size_t(nq) * M);
        std::vector<float> xt(size_t(len) * qp), nx(qp), rx(qp), minhi(qp), qq(qp);
        std::vector<float> c(size_t(kRowTile) * qp);
        std::vector<uint64_t> keep(size_t(kRowTile) * words);
        std::vector<uint8_t> ok(std::max<int64_t>(1, max_seg_len()));
        std::vector<float> scratch_a(ok.size()), scratch_b(ok.size());
        std::vector<int64_t> best(qp);
        std::vector<float> best_dp(qp);
        std::vector<double> best_da(qp);
        std::vector<int64_t> lanes;  // lane -> index in block
        // bit per lane: the step's lanes, and (M x words) the lanes excluded from each segment
        std::vector<uint64_t> valid(words), ex_bits(size_t(M) * words), inc(words);
        std::vector<QueryStep> lane_step(qp);
        // lanes whose kept candidates are recomputed in this segment (bit per
        // lane), and the lanes that scan every segment exactly (projection
        // bound not finite for their previous pose)
        std::vector<uint64_t> live(words), lane_ok(words);
        // projection filter: per-lane constants and the tile's masked |z|^2
        std::vector<float> lane_par(size_t(6) * qp), nrow_tile(kRowTile);
        const ProjLanes pl{&lane_par[0], &lane_par[qp], &lane_par[2 * qp], &lane_par[3 * qp],
                           &lane_par[4 * qp], &lane_par[5 * qp]};
        // the exact recomputation of one tile's kept (row, lane) pairs
        std::vector<const float*> pair_row(size_t(kRowTile) * qp), pair_vec(size_t(kRowTile) * qp);
        std::vector<int32_t> pair_lane(size_t(kRowTile) * qp), pair_r(size_t(kRowTile) * qp);
        std::vector<float> pair_d(size_t(kRowTile) * qp);
        // the other distance of each lane's pre-selected candidate in a segment
        std::vector<const float*> fin_a(qp), fin_b(qp);
        std::vector<int32_t> fin_lane(qp);
        std::vector<int64_t> fin_g(qp);
        std::vector<float> fin_qa(qp), fin_qq(qp), fin_aa(qp);
        std::vector<double> fin_da(qp);
        std::unique_ptr<StepEngine> single;  // partial windows
        Ranker ranker;

        for (int64_t step = 0; step < max_steps; ++step) {
            const int64_t t = step * N_;
            const BitsetView allowed = allowed_steps.at(step);
            lanes.clear();
            for (int64_t i = 0; i < nq; ++i) {
                if (step >= S[i] || block[i]->failed_step >= 0) continue;
                const int64_t n = std::min(N_, block[i]->audio.rows - t);
                if (n == N_) {
                    lanes.push_back(i);
                    continue;
                }
                // the last, partial window of this query: one exact step
                if (!single) single.reset(new StepEngine(kern_, db_, 1));
                StepOptions opt;
                opt.k = block[i]->k;
                opt.preselect = pre_;
                opt.allowed = allowed;
                opt.exclude = block[i]->exclude;
                if (block[i]->table_s != nullptr) {
                    single->preselect(prev[i], block[i]->audio.row(t), n, opt, block[i]->table_s,
                                      block[i]->table_dp, block[i]->table_da);
                    continue;
                }
                const StepResult r = single->step(prev[i], block[i]->audio.row(t), n, opt);
                finish(block[i], step, t, r, prev[i]);
            }
            const int64_t nl = int64_t(lanes.size());
            if (nl == 0) continue;
            // lanes of this step, and per segment the lanes excluded from it (one
            // scan of each lane's exclusion row per step instead of a load per
            // lane and segment)
            std::fill(valid.begin(), valid.end(), uint64_t(0));
            for (int64_t l = 0; l < nl; ++l) valid[l / 64] |= uint64_t(1) << (l % 64);
            bool any_ex = false;
            for (int64_t l = 0; l < nl; ++l) any_ex |= block[lanes[l]]->exclude != nullptr;
            if (any_ex) {
                std::fill(ex_bits.begin(), ex_bits.end(), uint64_t(0));
                for (int64_t l = 0; l < nl; ++l)
                    if (const bool* ex = block[lanes[l]]->exclude) mark_excluded(ex, M, l, words, ex_bits.data());
            }

            // the panel: one column per lane (padding lanes are zero and ignored)
            std::fill(xt.begin(), xt.end(), 0.0f);
            std::fill(nx.begin(), nx.end(), 0.0f);
            std::fill(rx.begin(), rx.end(), 0.0f);
            std::fill(lane_ok.begin(), lane_ok.end(), uint64_t(0));
            if (proj_) lane_defaults(lane_par, qp);
            for (int64_t l = 0; l < nl; ++l) {
                const BatchQuery* bq = block[lanes[l]];
                QueryStep& ls = lane_step[l];
                ls.prev = prev[lanes[l]];
                ls.q = bq->audio.row(t);
                ls.n = N_;
                ls.qq = query_norm2(kern_, ls.q, N_ * Da);
                float* panel = &xt[(l / 64) * 64 * len + (l % 64)];
                bool filtered = true;
                if (proj_) {
                    const ProjQuery pq = proj_query(db_, ls.prev);
                    filtered = lane_bounds(pq, lane_par, qp, l);
                    if (filtered)
                        for (int64_t p = 0; p < J; ++p) panel[p * 64] = pq.zx[p];
                } else {
                    const float* col = pre_ == Preselect::Pose ? ls.prev : ls.q;
                    for (int64_t p = 0; p < len; ++p) panel[p * 64] = col[p];
                    if (pre_ == Preselect::Pose) {
                        double s = 0.0;
                        for (int64_t p = 0; p < Dp; ++p) s += double(col[p]) * col[p];
                        nx[l] = float(s);
                        rx[l] = float(std::sqrt(s));
                    } else {
                        rx[l] = ls.qq > 0.0f ? 1.0f / std::sqrt(ls.qq) : 0.0f;
                    }
                }
                if (filtered) lane_ok[l / 64] |= uint64_t(1) << (l % 64);
            }

            for (int64_t l = 0; l < nl; ++l)
                std::fill(&sel_s[lanes[l] * M], &sel_s[lanes[l] * M] + M, int64_t(-1));
            for (int64_t m = 0; m < M; ++m) {
                const int64_t n_cand = db_.seg_len[m] - N_;
                const int64_t seg0 = db_.seg_start[m];
                if (m + 1 < M) prefetch_rows(m + 1);
                if (n_cand < 1) continue;
                bool any = false;
                const uint8_t* okp = nullptr;
                if (allowed.all()) {
                    any = true;
                } else {
                    std::fill(ok.begin(), ok.begin() + n_cand, uint8_t(0));
                    for_each_allowed_run(allowed, seg0 + 1, n_cand, N_ - 1, [&](int64_t i0, int64_t i1) {
                        std::fill(ok.begin() + i0, ok.begin() + i1, uint8_t(1));
                        any = true;
                    });
                    okp = ok.data();
                }
                if (!any) continue;
                // lanes in this segment (inc: not excluded from it) and those that
                // filter it (live: also a usable bound)
                const bool seg_filtered = !(proj_ && seg_bad_[m]);
                const uint64_t* exm = &ex_bits[size_t(m) * words];
                bool any_inc = false, any_live = false;
                for (int64_t w = 0; w < words; ++w) {
                    inc[w] = any_ex ? valid[w] & ~exm[w] : valid[w];
                    live[w] = seg_filtered ? lane_ok[w] & inc[w] : 0;
                    any_inc |= inc[w] != 0;
                    any_live |= live[w] != 0;
                }
                if (!any_inc) continue;

                std::fill(minhi.begin(), minhi.end(), std::numeric_limits<float>::infinity());
                std::fill(best.begin(), best.begin() + nl, int64_t(-1));
                for (int64_t i0 = 0; any_live && i0 < n_cand; i0 += kRowTile) {
                    const int64_t nr = std::min(kRowTile, n_cand - i0);
                    if (proj_) {
                        // rows are the entry frames g - 1 = seg0 + i; a row that is
                        // not a candidate gets |z|^2 = +inf: it neither bounds nor is kept
                        const float* nrow = &pr_->pnrow[seg0 + i0];
                        if (okp) {
                            const float inf = std::numeric_limits<float>::infinity();
                            for (int64_t r = 0; r < nr; ++r) nrow_tile[r] = okp[i0 + r] ? nrow[r] : inf;
                            nrow = nrow_tile.data();
                        }
                        if (tile_has_row(okp, i0, nr)) {
                            kern_.projfilter_f32(&pr_->zrow[(seg0 + i0) * J], nr, J, nrow, &pr_->rres[seg0 + i0],
                                                 xt.data(), qp, pl, c.data(), minhi.data());
                            kern_.projkeep_f32(c.data(), nr, qp, pl, minhi.data(), keep.data());
                        } else {
                            std::fill(keep.begin(), keep.begin() + nr * words, uint64_t(0));
                        }
                    } else if (pre_ == Preselect::Pose) {
                        // rows are the entry frames g - 1 = seg0 + i
                        kern_.dots_block_f32(db_.pose.row(seg0 + i0), nr, Dp, Dp, xt.data(), qp, c.data());
                        kern_.l2filter_f32(c.data(), nr, qp, &nrow_[seg0 + i0], &rrow_[seg0 + i0],
                                           okp ? okp + i0 : nullptr, nx.data(), rx.data(), eps_,
                                           minhi.data(), keep.data());
                    } else {
                        // rows are the windows starting at g = seg0 + 1 + i
                        kern_.dots_block_f32(db_.audio.row(seg0 + 1 + i0), nr, Da, len, xt.data(), qp, c.data());
                        kern_.cosfilter_f32(c.data(), nr, qp, nullptr, &rrow_[seg0 + 1 + i0],
                                            okp ? okp + i0 : nullptr, nullptr, rx.data(), eps_,
                                            minhi.data(), keep.data());
                    }
                    // exact values of the kept candidates, in ascending s per lane
                    const int64_t n_pairs =
                        collect_pairs(keep.data(), live.data(), nr, words, pair_lane.data(), pair_r.data());
                    if (pre_ == Preselect::Audio) {
                        for (int64_t p = 0; p < n_pairs; ++p)
                            exact_update_audio(m, i0 + pair_r[p], lane_step[pair_lane[p]], pair_lane[p], best,
                                               best_da);
                    } else if (n_pairs > 0) {
                        const float* rows = db_.pose.row(seg0 + i0);
                        const int64_t stride = db_.pose.cols;
                        for (int64_t p = 0; p < n_pairs; ++p) {
                            pair_row[p] = rows + pair_r[p] * stride;
                            pair_vec[p] = lane_step[pair_lane[p]].prev;
                        }
                        kern_.l2sq_pairs_f32(pair_row.data(), pair_vec.data(), n_pairs, Dp, pair_d.data());
                        for (int64_t p = 0; p < n_pairs; ++p) {
                            const int32_t l = pair_lane[p];
                            const float d = pair_d[p], bd = best_dp[l];
                            // nan_last_less with ties to the smaller s (the pairs come
                            // in ascending s per lane); branch-free, as the outcome is
                            // unpredictable
                            // (masks rather than ?: so that the compiler does not
                            // turn it back into branches)
                            const int64_t better =
                                int64_t(best[l] < 0) | int64_t(d < bd) | (int64_t(bd != bd) & int64_t(d == d));
                            const int64_t mask = -better;
                            best[l] = ((i0 + int64_t(pair_r[p])) & mask) | (best[l] & ~mask);
                            uint32_t db, bb;
                            std::memcpy(&db, &d, 4);
                            std::memcpy(&bb, &bd, 4);
                            const uint32_t out = (db & uint32_t(mask)) | (bb & ~uint32_t(mask));
                            std::memcpy(&best_dp[l], &out, 4);
                        }
                    }
                }
                int64_t n_fin = 0;
                for (int64_t w = 0; w < words; ++w)
                for (uint64_t bits = inc[w]; bits; bits &= bits - 1) {
                    const int64_t l = w * 64 + __builtin_ctzll(bits);
                    const int64_t qi = lanes[l];
                    Selection sel{&sel_s[qi * M], &sel_dp[qi * M], &sel_da[qi * M]};
                    int64_t b;
                    const bool filtered = (live[w] >> (l % 64)) & 1;
                    if (!filtered || !(minhi[l] < std::numeric_limits<float>::infinity())) {
                        // a non-finite approximate distance or bound: it says
                        // nothing, so this lane scans the segment exactly
                        b = preselect_exact(kern_, db_, m, lane_step[l], pre_, allowed,
                                            scratch_a.data(), scratch_b.data(), sel);
                    } else {
                        b = best[l];
                        if (pre_ == Preselect::Pose) sel.dp[m] = best_dp[l];
                        else sel.da[m] = best_da[l];
                    }
                    if (b < 0) continue;
                    sel.s[m] = b + 1;
                    // the other distance, for all lanes at once below
                    const int64_t g = seg0 + b + 1;
                    fin_lane[n_fin] = int32_t(l);
                    fin_g[n_fin] = g;
                    if (pre_ == Preselect::Pose) {
                        fin_a[n_fin] = db_.audio.row(g);
                        fin_b[n_fin] = lane_step[l].q;
                    } else {
                        fin_a[n_fin] = db_.pose.row(g - 1);
                        fin_b[n_fin] = lane_step[l].prev;
                    }
                    ++n_fin;
                }
                if (pre_ == Preselect::Pose) {
                    kern_.cosdots_pairs_f32(fin_a.data(), fin_b.data(), n_fin, N_ * Da, fin_qa.data());
                    for (int64_t i = 0; i < n_fin; ++i) {
                        fin_qq[i] = lane_step[fin_lane[i]].qq;
                        fin_aa[i] = wnorm_[fin_g[i]];
                    }
                    cosine_distances(fin_qa.data(), fin_qq.data(), fin_aa.data(), fin_da.data(), n_fin);
                    for (int64_t i = 0; i < n_fin; ++i) sel_da[lanes[fin_lane[i]] * M + m] = fin_da[i];
                } else {
                    kern_.l2sq_pairs_f32(fin_a.data(), fin_b.data(), n_fin, Dp, fin_qa.data());
                    for (int64_t i = 0; i < n_fin; ++i) sel_dp[lanes[fin_lane[i]] * M + m] = fin_qa[i];
                }
            }
            for (int64_t l = 0; l < nl; ++l) {
                const int64_t qi = lanes[l];
                Selection sel{&sel_s[qi * M], &sel_dp[qi * M], &sel_da[qi * M]};
                if (BatchQuery* bq = block[qi]; bq->table_s != nullptr) {
                    // a pre-selection table (BatchPlan::preselect): as StepEngine::preselect writes it
                    for (int64_t m = 0; m < M; ++m) {
                        bq->table_s[m] = sel.s[m];
                        bq->table_dp[m] = sel.s[m] >= 0 ? sel.dp[m] : 0.0f;
                        bq->table_da[m] = sel.s[m] >= 0 ? sel.da[m] : 0.0;
                    }
                    continue;
                }
                const StepResult r = ranker.rank(db_, sel, N_, block[qi]->k);
                finish(block[qi], step, t, r, prev[qi]);
            }
        }
    }

private:
    // ProjRows of db; a frame whose |z_f|^2 is not finite or above kProjBig
    // (or whose residual is not finite) is marked unusable.
    static std::shared_ptr<const ProjRows> build_proj_rows(const Database& db, int threads) {
        const int64_t F = db.n_frames(), J = db.proj_dim;
        auto pr = std::make_shared<ProjRows>();
        pr->zrow.assign(size_t(std::max<int64_t>(F, 1)) * J, 0.0f);
        pr->pnrow.assign(std::max<int64_t>(F, 1), 0.0f);
        pr->rres.assign(std::max<int64_t>(F, 1), 0.0f);
        std::vector<uint8_t> bad(std::max<int64_t>(F, 1), 0);
        const int64_t chunk = 1 << 14;
        const int64_t n_chunks = (F + chunk - 1) / chunk;
        std::vector<double> zmax(std::max<int64_t>(n_chunks, 1), 0.0);
        parallel_for(n_chunks, threads, [&](int64_t c, int) {
            const int64_t f0 = c * chunk, f1 = std::min(F, f0 + chunk);
            for (int64_t f = f0; f < f1; ++f) {
                double s = 0.0;
                for (int64_t j = 0; j < J; ++j) {
                    const float v = db.proj_value(f, j);
                    pr->zrow[f * J + j] = v;
                    s += double(v) * double(v);
                }
                pr->rres[f] = pr->zrow[f * J + J - 1];
                if (!(s <= kProjBig) || !std::isfinite(double(pr->rres[f]))) {
                    bad[f] = 1;
                    pr->pnrow[f] = 0.0f;
                } else {
                    pr->pnrow[f] = float(s);
                    zmax[c] = std::max(zmax[c], std::sqrt(s));
                }
            }
        });
        for (double z : zmax) pr->zmax = std::max(pr->zmax, z);
        pr->zmax *= 1.0 + 1e-6;  // and the rounding of the sums
        pr->n_bad.assign(F + 1, 0);
        for (int64_t f = 0; f < F; ++f) pr->n_bad[f + 1] = pr->n_bad[f] + bad[f];
        const double u = std::ldexp(1.0, -24);
        const double gamma = double(J + 8) * u / (1.0 - double(J + 8) * u);
        pr->eps = 4.0 * gamma;
        return pr;
    }

    // Harmless constants for lanes that do not filter (padding, exact lanes):
    // their bits are never read, and every value stays finite.
    static void lane_defaults(std::vector<float>& par, int64_t qp) {
        std::fill(par.begin(), par.end(), 0.0f);
        std::fill(par.begin() + 1 * qp, par.begin() + 2 * qp, 1.0f);  // aup
        std::fill(par.begin() + 4 * qp, par.begin() + 5 * qp, 1.0f);  // alo
    }

    // The constants of lane l's bounds for the blocked form of the projection
    // filter; false when they are not usable (the lane scans exactly).
    //
    // proj_filter bounds the exact float32 distance by a_lo Lh - c_lo and
    // a_up Lh + b_up r_f + c_up, Lh being a float32 sum within gk of
    // D = |z_f - z_x|^2 (z_f, z_x the stored float32 values). Here D comes as
    // Dh = |z_f|^2 + |z_x|^2 - 2 <z_f, z_x> from a blocked float32 dot product:
    // each term and the dot product are within gamma_{J+2} (|z_f| + |z_x|)^2
    // of their real values, so |Dh - D| <= b = 4 gamma_{J+8} (Zmax + |z_x|)^2
    // (twice that margin; Zmax >= every |z_f| the filter reads), one constant
    // per lane. With D in [Dh - b, Dh + b]:
    //   lower  a_lo Dh - (c_lo + 2 a_lo b)   <= a_lo D - c_lo  (also when Dh < 0,
    //          where the extra a_lo b covers a_lo's rounding margin),
    //   upper  a_up Dh + b_up r_f + (c_up + 2 a_up b) >= a_up D + b_up r_f + c_up,
    // the constants rounded outwards, and the float evaluation of each (three
    // roundings) is covered as in proj_query by a_lo's (1 - 8u), a_up's
    // (1 + 4u) and the factor 2 on the b terms. No value can overflow: every
    // |z|^2 in play is at most kProjBig and the largest upper bound is checked.
    bool lane_bounds(const ProjQuery& pq, std::vector<float>& par, int64_t qp, int64_t l) const {
        if (!pq.ok) return false;
        const int64_t J = db_.proj_dim;
        double zx2 = 0.0;
        for (int64_t p = 0; p < J; ++p) zx2 += double(pq.zx[p]) * double(pq.zx[p]);
        if (!(zx2 <= kProjBig)) return false;
        const double u = std::ldexp(1.0, -24);
        const double zx = std::sqrt(zx2);
        const double zmax = pr_->zmax;
        const double b = pr_->eps * (zmax + zx) * (zmax + zx);
        const float inf = std::numeric_limits<float>::infinity();
        auto up = [&](double v) {
            float f = float(v);
            if (double(f) < v) f = std::nextafter(f, inf);
            return f;
        };
        const double aup = pq.a_up, alo = pq.a_lo;
        const float cup = up((double(pq.c_up) + 2.0 * aup * b) * (1.0 + 8.0 * u));
        const float clo = up((double(pq.c_lo) + 2.0 * alo * b) * (1.0 + 8.0 * u));
        // the largest value the upper bound can take (|Dh| <= (Zmax + |z_x|)^2 + b)
        const double ub_max = aup * ((zmax + zx) * (zmax + zx) + b) + double(pq.b_up) * zmax + cup;
        if (!(alo > 0.0) || !(aup > 0.0) || !(ub_max < 1e36) || !std::isfinite(double(clo))) return false;
        par[0 * qp + l] = float(zx2);
        par[1 * qp + l] = pq.a_up;
        par[2 * qp + l] = pq.b_up;
        par[3 * qp + l] = cup;
        par[4 * qp + l] = pq.a_lo;
        par[5 * qp + l] = clo;
        return true;
    }

    // Sets lane l's bit in ex_bits[m * words + l / 64] for every segment m with ex[m]
    // (bool rows are mostly zero: eight at a time).
    static void mark_excluded(const bool* ex, int64_t M, int64_t l, int64_t words, uint64_t* ex_bits) {
        const uint64_t bit = uint64_t(1) << (l % 64);
        uint64_t* col = ex_bits + l / 64;
        int64_t m = 0;
        for (; m + 8 <= M; m += 8) {
            uint64_t v;
            std::memcpy(&v, ex + m, 8);
            if (v == 0) continue;
            for (int64_t j = 0; j < 8; ++j)
                if (ex[m + j]) col[(m + j) * words] |= bit;
        }
        for (; m < M; ++m)
            if (ex[m]) col[m * words] |= bit;
    }

    // The kept (row, lane) pairs of a tile, row by row (so each lane's rows come
    // in ascending s, which the strict minimum's tie rule needs). Still about a
    // fifth of run()'s own time (perf): about two bits per word, so each word's
    // loop exit is hard to predict.
    static int64_t collect_pairs(const uint64_t* __restrict keep, const uint64_t* __restrict live, int64_t nr,
                                 int64_t words, int32_t* __restrict pair_lane, int32_t* __restrict pair_r) {
        int64_t n = 0;
        for (int64_t r = 0; r < nr; ++r, keep += words)
            for (int64_t w = 0; w < words; ++w)
                for (uint64_t bits = keep[w] & live[w]; bits; bits &= bits - 1) {
                    pair_lane[n] = int32_t(w * 64 + __builtin_ctzll(bits));
                    pair_r[n] = int32_t(r);
                    ++n;
                }
        return n;
    }

    static bool tile_has_row(const uint8_t* okp, int64_t i0, int64_t nr) {
        if (okp == nullptr) return true;
        for (int64_t r = 0; r < nr; ++r)
            if (okp[i0 + r]) return true;
        return false;
    }

    // The rows the next segment will read outside the streamed matrix: the
    // winners' other distance (audio windows in pose mode, entry poses in audio
    // mode), one per lane at scattered offsets, and with the projection the
    // kept entry poses. Fetching them while this segment is filtered turns
    // those cache misses into hits.
    void prefetch_rows(int64_t m) const {
        const int64_t n_cand = db_.seg_len[m] - N_;
        if (n_cand < 1) return;
        auto fetch = [](const float* a, const float* b) {
            for (const char* p = reinterpret_cast<const char*>(a); p < reinterpret_cast<const char*>(b); p += 64)
                __builtin_prefetch(p);
        };
        const int64_t seg0 = db_.seg_start[m];
        if (pre_ == Preselect::Pose) {
            fetch(db_.audio.row(seg0 + 1), db_.audio.row(seg0 + 1 + n_cand + N_));
            if (proj_) fetch(db_.pose.row(seg0), db_.pose.row(seg0 + n_cand));
        } else {
            fetch(db_.pose.row(seg0), db_.pose.row(seg0 + n_cand));
        }
    }

    int64_t max_seg_len() const {
        int64_t mx = 0;
        for (int64_t m = 0; m < db_.n_segments(); ++m) mx = std::max(mx, db_.seg_len[m]);
        return mx;
    }

    // The exact audio distance of candidate i of segment m for one lane, folded
    // into the lane's running minimum (strict: ties keep the smaller s).
    void exact_update_audio(int64_t m, int64_t i, const QueryStep& qs, int64_t l, std::vector<int64_t>& best,
                            std::vector<double>& best_da) const {
        const int64_t seg0 = db_.seg_start[m];
        float qa, aa;
        kern_.cosdots_f32(db_.audio.row(seg0 + 1 + i), 1, db_.audio.cols, qs.n * db_.audio.cols, qs.q, &qa, &aa);
        const double d = cosine_distance(qa, qs.qq, aa);
        if (best[l] < 0 || nan_last_less(d, best_da[l])) {
            best[l] = i;
            best_da[l] = d;
        }
    }

    void finish(BatchQuery* bq, int64_t step, int64_t t, const StepResult& r, const float*& prev) const {
        if (!r.found) {
            bq->failed_step = step;
            return;
        }
        write_step(bq->out, step, t, r);
        prev = db_.pose.row(r.frame + r.length - 1);
    }

    const Kernels& kern_;
    const Database& db_;
    int64_t N_;
    Preselect pre_;
    std::vector<float> nrow_, rrow_;
    std::vector<float> wnorm_;  // pose mode: <a, a> of the N-frame audio window at each frame
    float eps_ = 0.0f;
    // the projection filter (proj_: pose pre-selection with Database::proj)
    bool proj_ = false;
    std::shared_ptr<const ProjRows> pr_;
    std::vector<uint8_t> seg_bad_;
};

}  // namespace

int64_t rank_sum_search(const Kernels& kernels, const Database& db, Span2<const float> query,
                        const float* init_pose, int64_t window, int64_t k, Preselect preselect,
                        const AllowedSchedule& allowed, const bool* exclude,
                        const SearchOutput& out, int threads) {
    check_search_args(db, query, window, k, allowed);
    StepEngine engine(kernels, db, threads <= 0 ? default_threads() : threads);
    return run_search(engine, db, query, init_pose, window, k, preselect, allowed, exclude, out);
}

namespace {

BatchMethod resolve_method(const Kernels& kernels, int64_t Q, BatchMethod method) {
    if (method != BatchMethod::Auto) return method;
    // the blocked filter pays off once a panel holds enough queries to share
    // each candidate row; the scalar table has no fast block kernel
    const bool scalar = std::strcmp(kernels.isa, "scalar") == 0;
    return (!scalar && Q >= 16) ? BatchMethod::Blocked : BatchMethod::PerQuery;
}

// blocked: the set-up for this window when method resolves to Blocked (null:
// built for this call).
void run_batch(const Kernels& kernels, const Database& db, std::vector<BatchQuery>& queries, int64_t window,
               Preselect preselect, const AllowedSchedule& allowed, int threads, BatchMethod method,
               const BlockedBatch* blocked = nullptr) {
    if (threads <= 0) threads = default_threads();
    const int64_t Q = int64_t(queries.size());
    if (Q == 0) return;
    method = resolve_method(kernels, Q, method);
    if (method == BatchMethod::PerQuery) {
        threads = int(std::min<int64_t>(threads, Q));
        // one engine per worker, each single-threaded: parallel over queries only
        std::vector<std::unique_ptr<StepEngine>> engines(threads);
        for (auto& e : engines) e.reset(new StepEngine(kernels, db, 1));
        parallel_for(Q, threads, [&](int64_t i, int tid) {
            BatchQuery& q = queries[i];
            if (q.table_s != nullptr) {
                StepOptions opt;
                opt.preselect = preselect;
                opt.allowed = allowed.at(0);
                opt.exclude = q.exclude;
                engines[tid]->preselect(q.init_pose, q.audio.data, q.audio.rows, opt, q.table_s, q.table_dp,
                                        q.table_da);
                return;
            }
            q.failed_step = run_search(*engines[tid], db, q.audio, q.init_pose, window, q.k,
                                       preselect, allowed, q.exclude, q.out);
        });
        return;
    }
    std::unique_ptr<BlockedBatch> own;
    if (blocked == nullptr) {
        own.reset(new BlockedBatch(kernels, db, window, preselect, threads));
        blocked = own.get();
    }
    // blocks of up to 256 queries, at least one block per thread, and at most
    // ~64 MB of per-segment pre-selection state (20 bytes per query and segment)
    // per block, so a database of many short segments does not exhaust memory
    const int64_t by_memory = std::max<int64_t>(16, (int64_t(64) << 20) / (20 * std::max<int64_t>(1, db.n_segments())));
    const int64_t per_block =
        std::max<int64_t>(1, std::min({int64_t(256), by_memory, (Q + threads - 1) / threads}));
    const int64_t n_blocks = (Q + per_block - 1) / per_block;
    std::vector<BatchQuery*> ptrs(Q);
    for (int64_t i = 0; i < Q; ++i) ptrs[i] = &queries[i];
    parallel_for(n_blocks, threads, [&](int64_t b, int) {
        const int64_t i0 = b * per_block, i1 = std::min(Q, i0 + per_block);
        blocked->run(ptrs.data() + i0, i1 - i0, allowed);
    });
}

// BatchPlan::preselect's checks; returns the windows' common length n.
int64_t check_table_queries(const Database& db, std::vector<BatchQuery>& queries, const AllowedSchedule& allowed) {
    const int64_t n = queries[0].audio.rows;
    if (n < 1) throw std::invalid_argument("queries: expected windows of >= 1 rows");
    if (allowed.per_step) throw std::invalid_argument("allowed: expected one bitset for a pre-selection table");
    for (auto& q : queries) {
        if (q.audio.rows != n)
            throw std::invalid_argument("queries: expected windows of equal length " + std::to_string(n) +
                                        "; got " + std::to_string(q.audio.rows));
        if (q.table_s == nullptr || q.table_dp == nullptr || q.table_da == nullptr)
            throw std::invalid_argument("BatchPlan::preselect: every query needs its table rows");
        q.k = 1;
        check_search_args(db, q.audio, n, 1, allowed);
    }
    return n;
}

}  // namespace

void rank_sum_search_batch(const Kernels& kernels, const Database& db,
                           std::vector<BatchQuery>& queries, int64_t window, Preselect preselect,
                           const AllowedSchedule& allowed, int threads, BatchMethod method) {
    for (auto& q : queries) {
        check_search_args(db, q.audio, window, q.k, allowed);
        q.table_s = nullptr;
    }
    run_batch(kernels, db, queries, window, preselect, allowed, threads, method);
}

// ---------------------------------------------------------------------------
struct BatchPlan::Impl {
    const Kernels& kern;
    Database db;
    Preselect pre;
    std::mutex mutex;  // guards blocked (calls may come from several threads)
    std::map<int64_t, std::shared_ptr<const BlockedBatch>> blocked;  // by window length

    Impl(const Kernels& k, const Database& d, Preselect p) : kern(k), db(d), pre(p) {}

    // The blocked set-up for windows of n rows, built on first use; every
    // window length shares the first one's projection rows.
    std::shared_ptr<const BlockedBatch> get(int64_t n, int threads) {
        std::lock_guard<std::mutex> lock(mutex);
        auto it = blocked.find(n);
        if (it != blocked.end()) return it->second;
        std::shared_ptr<const BlockedBatch::ProjRows> rows;
        if (!blocked.empty()) rows = blocked.begin()->second->proj_rows();
        auto b = std::make_shared<const BlockedBatch>(kern, db, n, pre, threads, rows);
        blocked.emplace(n, b);
        return b;
    }
};

BatchPlan::BatchPlan(const Kernels& kernels, const Database& db, Preselect preselect)
    : impl_(new Impl(kernels, db, preselect)) {
    check_database(db);
}

BatchPlan::~BatchPlan() = default;

void BatchPlan::preselect(std::vector<BatchQuery>& queries, const AllowedSchedule& allowed, int threads,
                          BatchMethod method) {
    if (queries.empty()) return;
    const int64_t n = check_table_queries(impl_->db, queries, allowed);
    if (threads <= 0) threads = default_threads();
    method = resolve_method(impl_->kern, int64_t(queries.size()), method);
    std::shared_ptr<const BlockedBatch> b;
    if (method == BatchMethod::Blocked) b = impl_->get(n, threads);
    run_batch(impl_->kern, impl_->db, queries, n, impl_->pre, allowed, threads, method, b.get());
}

int64_t BatchPlan::n_setups() const {
    std::lock_guard<std::mutex> lock(impl_->mutex);
    return int64_t(impl_->blocked.size());
}

}  // namespace gesturedb
