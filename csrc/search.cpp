// The search loop (search.h: rank_sum_search): steps at t = 0, N, 2N, ...,
// each continuing from the last frame the previous one copied.
#include "search.h"
#include "search_loop.h"
#include "threads.h"

#include <algorithm>
#include <stdexcept>
#include <string>

namespace gesturedb {

int64_t run_search(StepEngine& engine, const Database& db, Span2<const float> query, const float* init_pose,
                   int64_t window, int64_t k, Preselect preselect, const AllowedSchedule& allowed,
                   const bool* exclude, const SearchOutput& out) {
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

int64_t rank_sum_search(const Kernels& kernels, const Database& db, Span2<const float> query,
                        const float* init_pose, int64_t window, int64_t k, Preselect preselect,
                        const AllowedSchedule& allowed, const bool* exclude, const SearchOutput& out,
                        int threads) {
    check_search_args(db, query, window, k, allowed);
    StepEngine engine(kernels, db, threads <= 0 ? default_threads() : threads);
    return run_search(engine, db, query, init_pose, window, k, preselect, allowed, exclude, out);
}

}  // namespace gesturedb
