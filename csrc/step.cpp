// StepEngine (search.h): one step of one query over the whole database. The
// segments are cut into chunks of similar frame counts and handed to the pool
// (pool.h); in each chunk the pre-selection streams the candidates (exactly, or
// through a bounded filter of filters.h), then reads the scattered rows that
// decide, and the ranker (rank.h) picks the window.
#include "filters.h"
#include "pool.h"
#include "prefetch.h"
#include "preselect.h"
#include "rank.h"
#include "search.h"

#include <algorithm>
#include <cmath>
#include <memory>
#include <stdexcept>
#include <vector>

namespace gesturedb {
namespace {

// Below this many values per step the thread start-up costs more than it saves.
constexpr int64_t kMinParallelWork = int64_t(1) << 17;

}  // namespace

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
                        prefetch_bytes(db.pose.row(db.seg_start[m] + kept[j]),
                                       db.pose.cols * int64_t(sizeof(float)));
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
            if (!opt.other) return;  // the table without its other distance (StepOptions::other)
            for (int64_t m = m0; m < std::min(m1, m0 + kScatterAhead); ++m)
                prefetch_other(db, m, qs, opt.preselect, sel);
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

StepResult StepEngine::step(const float* prev, const float* query, int64_t n, const StepOptions& opt) {
    if (n < 1) throw std::invalid_argument("step: window length must be >= 1");
    return impl_->step(prev, query, n, opt);
}

void StepEngine::preselect(const float* prev, const float* query, int64_t n, const StepOptions& opt,
                           int64_t* start, float* pose_dist, double* audio_dist) {
    if (n < 1) throw std::invalid_argument("step: window length must be >= 1");
    const Selection sel = impl_->preselect(prev, query, n, opt);
    const int64_t M = impl_->db.n_segments();
    std::copy(sel.s, sel.s + M, start);
    // without the other distance (opt.other false) it is 0, as where no candidate was kept
    const bool dp = opt.other || opt.preselect == Preselect::Pose;
    const bool da = opt.other || opt.preselect == Preselect::Audio;
    for (int64_t m = 0; m < M; ++m) {
        pose_dist[m] = sel.s[m] >= 0 && dp ? sel.dp[m] : 0.0f;
        audio_dist[m] = sel.s[m] >= 0 && da ? sel.da[m] : 0.0;
    }
}

}  // namespace gesturedb
