// BlockedBatch's run (blocked.h): a block of queries advances step by step
// together. Each step takes its lanes (the queries with a full window; a
// partial last window takes the single path), loads their panel, pre-selects
// every segment for all lanes at once (the blocked filter in tiles of
// candidates, the exact recomputation of what it keeps, then each lane's
// candidate and its other distance) and ranks each lane.
#include "blocked.h"
#include "allowed.h"
#include "order.h"
#include "prefetch.h"
#include "preselect.h"
#include "rank.h"
#include "search_loop.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <memory>

namespace gesturedb {

namespace {
template <class... V>
void resize_each(size_t n, V&... v) {
    (v.resize(n), ...);
}
}  // namespace

struct BlockedBatch::Run {
    BatchQuery* const* block;
    int64_t nq;
    int64_t M, Dp, Da, J;
    // the step's lanes padded to a panel width (padded_lanes: 8, 16, 32 or
    // whole panels of 64) and 64-bit words of a bit per lane; the buffers are
    // sized for the block's queries, the widths set per step (set_width) so that
    // a step with few lanes filters with a narrow panel
    int64_t qp_max, words_max;
    int64_t qp = 0, words = 0;
    int64_t len = 0;                 // values per panel column: J, Dp or N * Da
    std::vector<const float*> prev;  // each query's previous pose
    std::vector<int64_t> S;          // each query's steps
    int64_t max_steps = 0;
    // the pre-selection of every query of the block, (nq, M) each
    std::vector<int64_t> sel_s;
    std::vector<float> sel_dp;
    std::vector<double> sel_da;
    std::vector<float> xt, nx, rx, minhi;
    std::vector<float> c;
    std::vector<uint64_t> keep;
    std::vector<uint8_t> ok;
    std::vector<float> scratch_a, scratch_b;
    std::vector<int64_t> best;
    std::vector<float> best_dp;
    std::vector<double> best_da;
    std::vector<int64_t> lanes;  // lane -> index in block
    // the step's distinct bitsets (views) and (views x words) the lanes of each;
    // per segment each view's allowed candidates (okbuf rows, view_okp: null
    // for all of them), whether it has any, and whether a group took it already
    std::vector<BitsetView> views;
    std::vector<uint64_t> view_lanes, group;
    std::vector<uint8_t> okbuf, view_any, view_done;
    std::vector<const uint8_t*> view_okp;
    // bit per lane: the step's lanes, and (M x words) the lanes excluded from each segment
    std::vector<uint64_t> valid, ex_bits, inc;
    std::vector<QueryStep> lane_step;
    // lanes whose kept candidates are recomputed in this segment (bit per
    // lane), and the lanes that scan every segment exactly (projection
    // bound not finite for their previous pose)
    std::vector<uint64_t> live, lane_ok;
    // projection filter: per-lane constants and the tile's masked |z|^2
    std::vector<float> lane_par, nrow_tile;
    ProjLanes pl;
    // the exact recomputation of one tile's kept (row, lane) pairs
    std::vector<const float*> pair_row, pair_vec;
    std::vector<int32_t> pair_lane, pair_r;
    std::vector<float> pair_d;
    // the other distance of each lane's pre-selected candidate in a segment
    std::vector<const float*> fin_a, fin_b;
    std::vector<int32_t> fin_lane;
    std::vector<int64_t> fin_g;
    std::vector<float> fin_qa, fin_qq, fin_aa;
    std::vector<double> fin_da;
    std::unique_ptr<StepEngine> single;  // partial windows
    Ranker ranker;
    // the step in progress: its output frame, lanes, and whether any lane excludes segments
    int64_t t = 0;
    int64_t nl = 0;
    bool any_ex = false;
    // the segment in progress: whether any lane filters it
    bool any_live = false;
    // whether any query wants its candidates' other distance (BatchQuery::table_other)
    bool any_other = false;

    Run(const BlockedBatch& b, BatchQuery* const* block_, int64_t nq_)
        : block(block_), nq(nq_), M(b.db_.n_segments()), Dp(b.db_.pose.cols), Da(b.db_.audio.cols),
          J(b.db_.proj_dim), qp_max(padded_lanes(nq)), words_max(lane_words(qp_max)), prev(nq), S(nq) {
        len = b.proj_ ? J : b.pre_ == Preselect::Pose ? Dp : b.N_ * Da;
        for (int64_t i = 0; i < nq; ++i) {
            prev[i] = block[i]->init_pose;
            S[i] = n_steps(block[i]->audio.rows, b.N_);
            block[i]->failed_step = -1;
            max_steps = std::max(max_steps, S[i]);
            any_other = any_other || block[i]->table_other;
        }
        // the buffers by their length: per query and segment, per lane, per word of lanes, per tile
        resize_each(size_t(nq) * M, sel_s, sel_dp, sel_da);
        resize_each(size_t(qp_max), nx, rx, minhi, best, best_dp, best_da, lane_step, fin_a, fin_b, fin_lane,
                    fin_g, fin_qa, fin_qq, fin_aa, fin_da);
        resize_each(size_t(words_max), valid, inc, group, live, lane_ok);
        resize_each(size_t(kRowTile) * qp_max, c, pair_row, pair_vec, pair_lane, pair_r, pair_d);
        xt.resize(size_t(len) * qp_max);
        keep.resize(size_t(kRowTile) * words_max);
        ok.resize(std::max<int64_t>(1, b.max_seg_len()));
        resize_each(ok.size(), scratch_a, scratch_b);
        ex_bits.resize(size_t(M) * words_max);
        lane_par.resize(size_t(6) * qp_max);
        nrow_tile.resize(kRowTile);
    }

    // The step's widths for nl lanes; pl then points at the lanes' constants
    // laid out for them.
    void set_width(int64_t nl) {
        qp = padded_lanes(nl);
        words = lane_words(qp);
        pl = ProjLanes{&lane_par[0],      &lane_par[qp],     &lane_par[2 * qp],
                       &lane_par[3 * qp], &lane_par[4 * qp], &lane_par[5 * qp]};
    }

    Run(const Run&) = delete;  // pl points into lane_par
    Run& operator=(const Run&) = delete;

    Selection selection(int64_t qi) { return Selection{&sel_s[qi * M], &sel_dp[qi * M], &sel_da[qi * M]}; }
};

void BlockedBatch::run(BatchQuery* const* block, int64_t nq, const AllowedSchedule& allowed_steps) const {
    Run r(*this, block, nq);
    for (int64_t step = 0; step < r.max_steps; ++step) {
        r.t = step * N_;
        if (take_lanes(r, step, allowed_steps) == 0) continue;
        r.set_width(r.nl);
        lane_views(r, allowed_steps.at(step));
        mark_lanes(r);
        load_panel(r);
        for (int64_t m = 0; m < r.M; ++m) {
            if (m + 1 < r.M) prefetch_rows(m + 1, r.any_other, r.nl);
            preselect_segment(r, m);
        }
        rank_lanes(r, step);
    }
}

// The step's lanes: every query with a full window at this step. A query in
// its last, partial window takes one exact step of the single path here.
// Returns the number of lanes.
int64_t BlockedBatch::take_lanes(Run& r, int64_t step, const AllowedSchedule& allowed_steps) const {
    BatchQuery* const* block = r.block;
    const int64_t t = r.t;
    r.lanes.clear();
    for (int64_t i = 0; i < r.nq; ++i) {
        if (step >= r.S[i] || block[i]->failed_step >= 0) continue;
        const int64_t n = std::min(N_, block[i]->audio.rows - t);
        if (n == N_) {
            r.lanes.push_back(i);
            continue;
        }
        // the last, partial window of this query: one exact step
        if (!r.single) r.single.reset(new StepEngine(kern_, db_, 1));
        StepOptions opt;
        opt.k = block[i]->k;
        opt.preselect = pre_;
        opt.allowed = query_allowed(*block[i], allowed_steps).at(step);
        opt.exclude = block[i]->exclude;
        opt.other = block[i]->table_other;
        if (block[i]->table_s != nullptr) {
            r.single->preselect(r.prev[i], block[i]->audio.row(t), n, opt, block[i]->table_s,
                                block[i]->table_dp, block[i]->table_da);
            continue;
        }
        const StepResult res = r.single->step(r.prev[i], block[i]->audio.row(t), n, opt);
        finish(block[i], step, t, res, r.prev[i]);
    }
    r.nl = int64_t(r.lanes.size());
    return r.nl;
}

// The step's distinct bitsets (a query's own or the batch's shared one, told
// apart by their words pointer) and the lanes of each.
void BlockedBatch::lane_views(Run& r, const BitsetView& shared) const {
    r.views.clear();
    r.view_lanes.clear();
    for (int64_t l = 0; l < r.nl; ++l) {
        const BatchQuery* bq = r.block[r.lanes[l]];
        const BitsetView v = bq->has_allowed ? bq->allowed : shared;
        size_t d = 0;
        while (d < r.views.size() && r.views[d].words != v.words) ++d;
        if (d == r.views.size()) {
            r.views.push_back(v);
            r.view_lanes.resize(r.view_lanes.size() + size_t(r.words), uint64_t(0));
        }
        r.view_lanes[d * size_t(r.words) + size_t(l / 64)] |= uint64_t(1) << (l % 64);
    }
    const size_t D = r.views.size();
    if (D > 1) {
        r.okbuf.resize(D * r.ok.size());
        r.view_okp.resize(D);
        r.view_any.resize(D);
        r.view_done.resize(D);
    }
}

// Lanes of this step, and per segment the lanes excluded from it (one scan of
// each lane's exclusion row per step instead of a load per lane and segment).
void BlockedBatch::mark_lanes(Run& r) const {
    const int64_t nl = r.nl;
    std::fill(r.valid.begin(), r.valid.end(), uint64_t(0));
    for (int64_t l = 0; l < nl; ++l) r.valid[l / 64] |= uint64_t(1) << (l % 64);
    r.any_ex = false;
    for (int64_t l = 0; l < nl; ++l) r.any_ex |= r.block[r.lanes[l]]->exclude != nullptr;
    if (r.any_ex) {
        std::fill(r.ex_bits.begin(), r.ex_bits.end(), uint64_t(0));
        for (int64_t l = 0; l < nl; ++l)
            if (const bool* ex = r.block[r.lanes[l]]->exclude)
                mark_excluded(ex, r.M, l, r.words, r.ex_bits.data());
    }
}

// The panel: one column per lane (padding lanes are zero and ignored), the
// lanes' norms or projection bounds, and their empty pre-selection tables.
void BlockedBatch::load_panel(Run& r) const {
    const int64_t nl = r.nl, len = r.len, qp = r.qp, Da = r.Da, Dp = r.Dp, J = r.J, M = r.M;
    const int64_t W = panel_width(qp);
    std::fill(r.xt.begin(), r.xt.begin() + len * qp, 0.0f);
    std::fill(r.nx.begin(), r.nx.begin() + qp, 0.0f);
    std::fill(r.rx.begin(), r.rx.begin() + qp, 0.0f);
    std::fill(r.lane_ok.begin(), r.lane_ok.begin() + r.words, uint64_t(0));
    if (proj_) lane_defaults(r.lane_par, qp);
    for (int64_t l = 0; l < nl; ++l) {
        const BatchQuery* bq = r.block[r.lanes[l]];
        QueryStep& ls = r.lane_step[l];
        ls.prev = r.prev[r.lanes[l]];
        ls.q = bq->audio.row(r.t);
        ls.n = N_;
        ls.qq = query_norm2(kern_, ls.q, N_ * Da);
        float* panel = &r.xt[panel_offset(l, len, W)];
        bool filtered = true;
        if (proj_) {
            const ProjQuery pq = proj_query(db_, ls.prev);
            filtered = lane_bounds(pq, r.lane_par, qp, l);
            if (filtered)
                for (int64_t p = 0; p < J; ++p) panel[p * W] = pq.zx[p];
        } else {
            const float* col = pre_ == Preselect::Pose ? ls.prev : ls.q;
            for (int64_t p = 0; p < len; ++p) panel[p * W] = col[p];
            if (pre_ == Preselect::Pose) {
                double s = 0.0;
                for (int64_t p = 0; p < Dp; ++p) s += double(col[p]) * col[p];
                r.nx[l] = float(s);
                r.rx[l] = float(std::sqrt(s));
            } else {
                r.rx[l] = ls.qq > 0.0f ? 1.0f / std::sqrt(ls.qq) : 0.0f;
            }
        }
        if (filtered) r.lane_ok[l / 64] |= uint64_t(1) << (l % 64);
    }
    for (int64_t l = 0; l < nl; ++l)
        std::fill(&r.sel_s[r.lanes[l] * M], &r.sel_s[r.lanes[l] * M] + M, int64_t(-1));
}

// Spec steps 1-3 of segment m for every lane of the step, a group of lanes
// (those whose bitsets allow the same candidates here) at a time.
void BlockedBatch::preselect_segment(Run& r, int64_t m) const {
    const int64_t n_cand = db_.seg_len[m] - N_;
    if (n_cand < 1) return;
    const size_t D = r.views.size();
    if (D == 1) {
        const uint8_t* okp = nullptr;
        if (allowed_candidates(m, r.views[0], r.ok.data(), okp))
            segment_group(r, m, r.views[0], okp, nullptr);
        return;
    }
    const size_t stride = r.ok.size();
    for (size_t d = 0; d < D; ++d) {
        r.view_any[d] = allowed_candidates(m, r.views[d], &r.okbuf[d * stride], r.view_okp[d]);
        // every candidate allowed reads as no mask, so that it groups with the lanes without one
        const uint8_t* p = r.view_okp[d];
        if (p != nullptr && std::find(p, p + n_cand, uint8_t(0)) == p + n_cand) r.view_okp[d] = nullptr;
        r.view_done[d] = 0;
    }
    for (size_t d = 0; d < D; ++d) {
        if (!r.view_any[d] || r.view_done[d]) continue;
        const uint8_t* pd = r.view_okp[d];
        std::copy(&r.view_lanes[d * r.words], &r.view_lanes[(d + 1) * r.words], r.group.begin());
        for (size_t e = d + 1; e < D; ++e) {
            const uint8_t* pe = r.view_okp[e];
            if (!r.view_any[e] || r.view_done[e]) continue;
            const bool same =
                (pd == nullptr || pe == nullptr) ? pd == pe : std::memcmp(pd, pe, size_t(n_cand)) == 0;
            if (!same) continue;
            for (int64_t w = 0; w < r.words; ++w) r.group[w] |= r.view_lanes[e * r.words + w];
            r.view_done[e] = 1;
        }
        // the group's candidates are the same under each of its bitsets: view d's stands for all
        segment_group(r, m, r.views[d], pd, r.group.data());
    }
}

// Segment m for the lanes of group (null: every lane), whose bitsets allow
// the candidates okp (null: all): the blocked filter over the segment's
// candidates in tiles, the exact recomputation of what it keeps, then each
// lane's pre-selected candidate and its other distance.
void BlockedBatch::segment_group(Run& r, int64_t m, const BitsetView& allowed, const uint8_t* okp,
                                 const uint64_t* group) const {
    const int64_t n_cand = db_.seg_len[m] - N_;
    if (!segment_lanes(r, m, group)) return;
    if (r.any_live && okp != nullptr && sparse_enough(r, okp, n_cand)) {
        // few candidates allowed: the group's lanes scan just those, exactly (choose_candidates)
        std::fill(r.live.begin(), r.live.end(), uint64_t(0));
        r.any_live = false;
    }
    std::fill(r.minhi.begin(), r.minhi.end(), std::numeric_limits<float>::infinity());
    std::fill(r.best.begin(), r.best.begin() + r.nl, int64_t(-1));
    for (int64_t i0 = 0; r.any_live && i0 < n_cand; i0 += kRowTile) {
        const int64_t nr = std::min(kRowTile, n_cand - i0);
        filter_tile(r, m, i0, nr, okp);
        recompute_kept(r, m, i0, nr);
    }
    const int64_t n_fin = choose_candidates(r, m, allowed);
    other_distances(r, m, n_fin);
}

// Whether the lanes in the segment (r.inc) scanning only the allowed
// candidates okp exactly cost less than the blocked filter over all of them:
// the filter reads every candidate row for each of the step's padded lanes
// (r.qp, r.len values a lane), the exact scan only the allowed rows for each
// lane (Dp pose values or an N-frame audio window). A control that keeps a
// few percent of the frames, or a group of a few lanes, is cheaper exactly.
bool BlockedBatch::sparse_enough(const Run& r, const uint8_t* okp, int64_t n_cand) const {
    int64_t n_ok = 0, lanes = 0;
    for (int64_t i = 0; i < n_cand; ++i) n_ok += okp[i];
    for (int64_t w = 0; w < r.words; ++w) lanes += __builtin_popcountll(r.inc[w]);
    const int64_t exact_len = pre_ == Preselect::Pose ? r.Dp : N_ * r.Da;
    return n_ok * lanes * exact_len < n_cand * r.qp * r.len;
}

// Which candidates of segment m the bitset allows: okp = null when all of
// them, else a byte per candidate in ok. False when none is.
bool BlockedBatch::allowed_candidates(int64_t m, const BitsetView& allowed, uint8_t* ok,
                                      const uint8_t*& okp) const {
    const int64_t n_cand = db_.seg_len[m] - N_;
    const int64_t seg0 = db_.seg_start[m];
    bool any = false;
    okp = nullptr;
    if (allowed.all()) {
        any = true;
    } else {
        std::fill(ok, ok + n_cand, uint8_t(0));
        for_each_allowed_run(allowed, seg0 + 1, n_cand, N_ - 1, [&](int64_t i0, int64_t i1) {
            std::fill(ok + i0, ok + i1, uint8_t(1));
            any = true;
        });
        okp = ok;
    }
    return any;
}

// Lanes of group (null: all) in segment m (inc: not excluded from it) and
// those that filter it (live: also a usable bound; r.any_live). False when no
// lane is in it.
bool BlockedBatch::segment_lanes(Run& r, int64_t m, const uint64_t* group) const {
    const bool seg_filtered = !(proj_ && seg_bad_[m]);
    const uint64_t* exm = &r.ex_bits[size_t(m) * r.words];
    bool any_inc = false, any_live = false;
    for (int64_t w = 0; w < r.words; ++w) {
        r.inc[w] = (r.any_ex ? r.valid[w] & ~exm[w] : r.valid[w]) & (group ? group[w] : ~uint64_t(0));
        r.live[w] = seg_filtered ? r.lane_ok[w] & r.inc[w] : 0;
        any_inc |= r.inc[w] != 0;
        any_live |= r.live[w] != 0;
    }
    r.any_live = any_live;
    return any_inc;
}

// The blocked filter over candidates [i0, i0 + nr) of segment m: every lane's
// approximate distance to each (r.c), the lanes' smallest upper bounds
// (r.minhi, running over the tiles) and the kept (row, lane) bits (r.keep).
void BlockedBatch::filter_tile(Run& r, int64_t m, int64_t i0, int64_t nr, const uint8_t* okp) const {
    const int64_t seg0 = db_.seg_start[m];
    const int64_t Dp = r.Dp, Da = r.Da, J = r.J, qp = r.qp;
    if (proj_) {
        // rows are the entry frames g - 1 = seg0 + i; a row that is
        // not a candidate gets |z|^2 = +inf: it neither bounds nor is kept
        const float* nrow = &pr_->pnrow[seg0 + i0];
        if (okp) {
            const float inf = std::numeric_limits<float>::infinity();
            for (int64_t k = 0; k < nr; ++k) r.nrow_tile[k] = okp[i0 + k] ? nrow[k] : inf;
            nrow = r.nrow_tile.data();
        }
        if (tile_has_row(okp, i0, nr)) {
            kern_.projfilter_f32(&pr_->zrow[(seg0 + i0) * J], nr, J, nrow, &pr_->rres[seg0 + i0], r.xt.data(),
                                 qp, r.pl, r.c.data(), r.minhi.data());
            kern_.projkeep_f32(r.c.data(), nr, qp, r.pl, r.minhi.data(), r.keep.data());
        } else {
            std::fill(r.keep.begin(), r.keep.begin() + nr * r.words, uint64_t(0));
        }
    } else if (pre_ == Preselect::Pose) {
        // rows are the entry frames g - 1 = seg0 + i
        kern_.dots_block_f32(db_.pose.row(seg0 + i0), nr, Dp, Dp, r.xt.data(), qp, r.c.data());
        kern_.l2filter_f32(r.c.data(), nr, qp, &nrow_[seg0 + i0], &rrow_[seg0 + i0], okp ? okp + i0 : nullptr,
                           r.nx.data(), r.rx.data(), eps_, r.minhi.data(), r.keep.data());
    } else {
        // rows are the windows starting at g = seg0 + 1 + i
        kern_.dots_block_f32(db_.audio.row(seg0 + 1 + i0), nr, Da, r.len, r.xt.data(), qp, r.c.data());
        kern_.cosfilter_f32(r.c.data(), nr, qp, nullptr, &rrow_[seg0 + 1 + i0], okp ? okp + i0 : nullptr,
                            nullptr, r.rx.data(), eps_, r.minhi.data(), r.keep.data());
    }
}

// Exact values of the tile's kept candidates for the live lanes, in ascending
// s per lane, folded into each lane's running minimum (r.best, r.best_dp or
// r.best_da).
void BlockedBatch::recompute_kept(Run& r, int64_t m, int64_t i0, int64_t nr) const {
    const int64_t seg0 = db_.seg_start[m];
    const int64_t n_pairs =
        collect_pairs(r.keep.data(), r.live.data(), nr, r.words, r.pair_lane.data(), r.pair_r.data());
    if (pre_ == Preselect::Audio) {
        for (int64_t p = 0; p < n_pairs; ++p)
            exact_update_audio(m, i0 + r.pair_r[p], r.lane_step[r.pair_lane[p]], r.pair_lane[p], r.best,
                               r.best_da);
    } else if (n_pairs > 0) {
        const float* rows = db_.pose.row(seg0 + i0);
        const int64_t stride = db_.pose.cols;
        for (int64_t p = 0; p < n_pairs; ++p) {
            r.pair_row[p] = rows + r.pair_r[p] * stride;
            r.pair_vec[p] = r.lane_step[r.pair_lane[p]].prev;
        }
        if (proj_ && r.nl < kPrefetchLanes) {
            // the kept rows at once, so that their misses overlap (prefetch_rows
            // fetched them only for a panel of lanes or more)
            int32_t last = -1;
            for (int64_t p = 0; p < n_pairs; ++p)
                if (r.pair_r[p] != last) {
                    last = r.pair_r[p];
                    prefetch_bytes(r.pair_row[p], stride * int64_t(sizeof(float)));
                }
        }
        kern_.l2sq_pairs_f32(r.pair_row.data(), r.pair_vec.data(), n_pairs, r.Dp, r.pair_d.data());
        for (int64_t p = 0; p < n_pairs; ++p) {
            const int32_t l = r.pair_lane[p];
            const float d = r.pair_d[p], bd = r.best_dp[l];
            // nan_last_less with ties to the smaller s (the pairs come
            // in ascending s per lane); branch-free, as the outcome is
            // unpredictable
            // (masks rather than ?: so that the compiler does not
            // turn it back into branches)
            const int64_t better =
                int64_t(r.best[l] < 0) | int64_t(d < bd) | (int64_t(bd != bd) & int64_t(d == d));
            const int64_t mask = -better;
            r.best[l] = ((i0 + int64_t(r.pair_r[p])) & mask) | (r.best[l] & ~mask);
            uint32_t db, bb;
            std::memcpy(&db, &d, 4);
            std::memcpy(&bb, &bd, 4);
            const uint32_t out = (db & uint32_t(mask)) | (bb & ~uint32_t(mask));
            std::memcpy(&r.best_dp[l], &out, 4);
        }
    }
}

// Each lane's pre-selected candidate of segment m: the minimum the filter
// left, or an exact scan where the filter said nothing. Lists the lanes with
// a candidate (r.fin_*) for their other distance; returns how many.
int64_t BlockedBatch::choose_candidates(Run& r, int64_t m, const BitsetView& allowed) const {
    const int64_t seg0 = db_.seg_start[m];
    int64_t n_fin = 0;
    for (int64_t w = 0; w < r.words; ++w)
        for (uint64_t bits = r.inc[w]; bits; bits &= bits - 1) {
            const int64_t l = w * 64 + __builtin_ctzll(bits);
            const int64_t qi = r.lanes[l];
            Selection sel = r.selection(qi);
            int64_t b;
            const bool filtered = (r.live[w] >> (l % 64)) & 1;
            if (!filtered || !(r.minhi[l] < std::numeric_limits<float>::infinity())) {
                // a non-finite approximate distance or bound: it says
                // nothing, so this lane scans the segment exactly
                b = preselect_exact(kern_, db_, m, r.lane_step[l], pre_, allowed, r.scratch_a.data(),
                                    r.scratch_b.data(), sel);
            } else {
                b = r.best[l];
                if (pre_ == Preselect::Pose) sel.dp[m] = r.best_dp[l];
                else sel.da[m] = r.best_da[l];
            }
            if (b < 0) continue;
            sel.s[m] = b + 1;
            if (!r.block[qi]->table_other) {  // a table without the other distance (StepOptions::other)
                if (pre_ == Preselect::Pose) sel.da[m] = 0.0;
                else sel.dp[m] = 0.0f;
                continue;
            }
            // the other distance, for all lanes at once in other_distances
            const int64_t g = seg0 + b + 1;
            r.fin_lane[n_fin] = int32_t(l);
            r.fin_g[n_fin] = g;
            if (pre_ == Preselect::Pose) {
                r.fin_a[n_fin] = db_.audio.row(g);
                r.fin_b[n_fin] = r.lane_step[l].q;
            } else {
                r.fin_a[n_fin] = db_.pose.row(g - 1);
                r.fin_b[n_fin] = r.lane_step[l].prev;
            }
            ++n_fin;
        }
    return n_fin;
}

// The other distance of the n_fin candidates choose_candidates listed, in one
// pair-kernel call.
void BlockedBatch::other_distances(Run& r, int64_t m, int64_t n_fin) const {
    const int64_t M = r.M;
    if (pre_ == Preselect::Pose) {
        kern_.cosdots_pairs_f32(r.fin_a.data(), r.fin_b.data(), n_fin, N_ * r.Da, r.fin_qa.data());
        for (int64_t i = 0; i < n_fin; ++i) {
            r.fin_qq[i] = r.lane_step[r.fin_lane[i]].qq;
            r.fin_aa[i] = wnorm_[r.fin_g[i]];
        }
        cosine_distances(r.fin_qa.data(), r.fin_qq.data(), r.fin_aa.data(), r.fin_da.data(), n_fin);
        for (int64_t i = 0; i < n_fin; ++i) r.sel_da[r.lanes[r.fin_lane[i]] * M + m] = r.fin_da[i];
    } else {
        kern_.l2sq_pairs_f32(r.fin_a.data(), r.fin_b.data(), n_fin, r.Dp, r.fin_qa.data());
        for (int64_t i = 0; i < n_fin; ++i) r.sel_dp[r.lanes[r.fin_lane[i]] * M + m] = r.fin_qa[i];
    }
}

// Spec steps 4-5 for each lane, or its pre-selection table when the block
// fills tables (BatchPlan::preselect).
void BlockedBatch::rank_lanes(Run& r, int64_t step) const {
    const int64_t M = r.M;
    for (int64_t l = 0; l < r.nl; ++l) {
        const int64_t qi = r.lanes[l];
        const Selection sel = r.selection(qi);
        if (BatchQuery* bq = r.block[qi]; bq->table_s != nullptr) {
            // a pre-selection table (BatchPlan::preselect): as StepEngine::preselect writes it
            for (int64_t m = 0; m < M; ++m) {
                bq->table_s[m] = sel.s[m];
                bq->table_dp[m] = sel.s[m] >= 0 ? sel.dp[m] : 0.0f;
                bq->table_da[m] = sel.s[m] >= 0 ? sel.da[m] : 0.0;
            }
            continue;
        }
        const StepResult res = r.ranker.rank(db_, sel, N_, r.block[qi]->k);
        finish(r.block[qi], step, r.t, res, r.prev[qi]);
    }
}

// Sets lane l's bit in ex_bits[m * words + l / 64] for every segment m with ex[m]
// (bool rows are mostly zero: eight at a time).
void BlockedBatch::mark_excluded(const bool* ex, int64_t M, int64_t l, int64_t words, uint64_t* ex_bits) {
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
int64_t BlockedBatch::collect_pairs(const uint64_t* __restrict keep, const uint64_t* __restrict live,
                                    int64_t nr, int64_t words, int32_t* __restrict pair_lane,
                                    int32_t* __restrict pair_r) {
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

bool BlockedBatch::tile_has_row(const uint8_t* okp, int64_t i0, int64_t nr) {
    if (okp == nullptr) return true;
    for (int64_t r = 0; r < nr; ++r)
        if (okp[i0 + r]) return true;
    return false;
}

// The rows the next segment will read outside the streamed matrix: the
// winners' other distance (audio windows in pose mode, entry poses in audio
// mode), one per lane at scattered offsets, and with the projection the
// kept entry poses. Fetching them while this segment is filtered turns
// those cache misses into hits. The entry poses only for kPrefetchLanes
// lanes or more: a lane keeps ~4 of a segment's ~56 candidates, so a few
// lanes read a few of its rows, and fetching every one of them (the whole
// pose matrix, 370 MB at 617k frames, each call) was ~20 ms of a 1-lane call.
void BlockedBatch::prefetch_rows(int64_t m, bool other, int64_t nl) const {
    const int64_t n_cand = db_.seg_len[m] - N_;
    if (n_cand < 1) return;
    auto fetch = [](const float* a, const float* b) {
        for (const char* p = reinterpret_cast<const char*>(a); p < reinterpret_cast<const char*>(b); p += 64)
            __builtin_prefetch(p);
    };
    const int64_t seg0 = db_.seg_start[m];
    if (pre_ == Preselect::Pose) {
        if (other) fetch(db_.audio.row(seg0 + 1), db_.audio.row(seg0 + 1 + n_cand + N_));
        if (proj_ && nl >= kPrefetchLanes) fetch(db_.pose.row(seg0), db_.pose.row(seg0 + n_cand));
    } else if (other) {
        fetch(db_.pose.row(seg0), db_.pose.row(seg0 + n_cand));
    }
}

int64_t BlockedBatch::max_seg_len() const {
    int64_t mx = 0;
    for (int64_t m = 0; m < db_.n_segments(); ++m) mx = std::max(mx, db_.seg_len[m]);
    return mx;
}

// The exact audio distance of candidate i of segment m for one lane, folded
// into the lane's running minimum (strict: ties keep the smaller s).
void BlockedBatch::exact_update_audio(int64_t m, int64_t i, const QueryStep& qs, int64_t l,
                                      std::vector<int64_t>& best, std::vector<double>& best_da) const {
    const int64_t seg0 = db_.seg_start[m];
    float qa, aa;
    kern_.cosdots_f32(db_.audio.row(seg0 + 1 + i), 1, db_.audio.cols, qs.n * db_.audio.cols, qs.q, &qa, &aa);
    const double d = cosine_distance(qa, qs.qq, aa);
    if (best[l] < 0 || nan_last_less(d, best_da[l])) {
        best[l] = i;
        best_da[l] = d;
    }
}

void BlockedBatch::finish(BatchQuery* bq, int64_t step, int64_t t, const StepResult& r,
                          const float*& prev) const {
    if (!r.found) {
        bq->failed_step = step;
        return;
    }
    write_step(bq->out, step, t, r);
    prev = db_.pose.row(r.frame + r.length - 1);
}
}  // namespace gesturedb
