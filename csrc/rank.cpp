// The ranker (rank.h) and the table forms of spec steps 4-5 that a sharded
// search merges with (search.h: rank_table, table_top_lists).
#include "rank.h"
#include "order.h"

#include <algorithm>
#include <limits>
#include <stdexcept>

namespace gesturedb {

StepResult Ranker::rank(const Database& db, const Selection& sel, int64_t n, int64_t k) {
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

bool Ranker::top_lists(int32_t K, int64_t k, int32_t& c, int64_t& rp_out, int64_t& ra_out) {
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

void Ranker::full(int32_t K, int64_t k, int32_t& c, int64_t& rp_out, int64_t& ra_out) {
    rp_.resize(K);
    ra_.resize(K);
    radix_order(kdp_.data(), K, ord_dp_, tmp_, hist_);
    for (int32_t i = 0; i < K; ++i) rp_[ord_dp_[i]] = i;
    radix_order(kda_.data(), K, ord_da_, tmp_, hist_);
    for (int32_t i = 0; i < K; ++i) ra_[ord_da_[i]] = i;
    // (R, rp) is unique (rp is a permutation), so it orders every candidate
    rkey_.resize(K);
    for (int32_t i = 0; i < K; ++i) rkey_[i] = (uint64_t(uint32_t(rp_[i] + ra_[i])) << 32) | uint32_t(rp_[i]);
    const int64_t kk = std::min<int64_t>(k, K) - 1;
    std::nth_element(rkey_.begin(), rkey_.begin() + kk, rkey_.end());
    c = ord_dp_[int32_t(rkey_[kk] & 0xFFFFFFFFu)];
    rp_out = rp_[c];
    ra_out = ra_[c];
}

TableRank rank_table(const int64_t* start, const float* pose_dist, const double* audio_dist, int64_t M,
                     int64_t k) {
    if (k < 1) throw std::invalid_argument("k: expected >= 1");
    if (M > int64_t(std::numeric_limits<int32_t>::max()))
        throw std::invalid_argument("table: expected fewer than 2^31 rows");
    // Kept per thread and reused: a live server ranks a step's table on its step thread every few
    // milliseconds, and buffers made afresh each call (about 0.5 MB at 10,000 segments) were allocated,
    // filled and freed every time (9,720 rows with cold caches: 0.61-1.02 ms a call, 0.36-0.56 kept).
    thread_local std::vector<int64_t> zero;
    thread_local Ranker ranker;
    if (int64_t(zero.size()) < std::max<int64_t>(M, 1)) zero.assign(std::max<int64_t>(M, 1), 0);
    // the ranker reads only the segment count and starts of a Database
    Database db;
    db.seg_start = {zero.data(), M};
    db.seg_len = {zero.data(), M};
    // Selection is read-only here; the ranker never writes through it
    Selection sel{const_cast<int64_t*>(start), const_cast<float*>(pose_dist),
                  const_cast<double*>(audio_dist)};
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
            select_smallest(
                a, int32_t(take), [](const std::pair<uint64_t, int32_t>& x) { return x.first; }, hist);
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

}  // namespace gesturedb
