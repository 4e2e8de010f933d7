// Batches (search.h: rank_sum_search_batch, BatchPlan): many queries, each
// returning exactly what it would alone. Chooses per batch between the
// per-query path (one single-threaded StepEngine per worker) and the blocked
// path (blocked.h), and cuts the queries into blocks for the pool.
#include "blocked.h"
#include "pool.h"
#include "search.h"
#include "search_loop.h"
#include "threads.h"

#include <algorithm>
#include <cstring>
#include <map>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <string>
#include <vector>

namespace gesturedb {
namespace {

BatchMethod resolve_method(const Kernels& kernels, int64_t Q, int threads, BatchMethod method) {
    if (method != BatchMethod::Auto) return method;
    // the blocked filter pays off once a block (run_batch: one per thread)
    // holds enough queries to share each candidate row; the scalar table has
    // no fast block kernel
    const bool scalar = std::strcmp(kernels.isa, "scalar") == 0;
    return (!scalar && Q >= blocked_min_queries(std::max(threads, 1))) ? BatchMethod::Blocked
                                                                       : BatchMethod::PerQuery;
}

// blocked: the set-up for this window when method resolves to Blocked (null:
// built for this call).
void run_batch(const Kernels& kernels, const Database& db, std::vector<BatchQuery>& queries, int64_t window,
               Preselect preselect, const AllowedSchedule& allowed, int threads, BatchMethod method,
               const BlockedBatch* blocked = nullptr) {
    if (threads <= 0) threads = default_threads();
    const int64_t Q = int64_t(queries.size());
    if (Q == 0) return;
    method = resolve_method(kernels, Q, threads, method);
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
                opt.allowed = query_allowed(q, allowed).at(0);
                opt.exclude = q.exclude;
                opt.other = q.table_other;
                engines[tid]->preselect(q.init_pose, q.audio.data, q.audio.rows, opt, q.table_s, q.table_dp,
                                        q.table_da);
                return;
            }
            q.failed_step = run_search(*engines[tid], db, q.audio, q.init_pose, window, q.k, preselect,
                                       query_allowed(q, allowed), q.exclude, q.out);
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
    const int64_t by_memory =
        std::max<int64_t>(16, (int64_t(64) << 20) / (20 * std::max<int64_t>(1, db.n_segments())));
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
int64_t check_table_queries(const Database& db, std::vector<BatchQuery>& queries,
                            const AllowedSchedule& allowed) {
    const int64_t n = queries[0].audio.rows;
    if (n < 1) throw std::invalid_argument("queries: expected windows of >= 1 rows");
    if (allowed.per_step)
        throw std::invalid_argument("allowed: expected one bitset for a pre-selection table");
    for (auto& q : queries) {
        if (q.audio.rows != n)
            throw std::invalid_argument("queries: expected windows of equal length " + std::to_string(n) +
                                        "; got " + std::to_string(q.audio.rows));
        if (q.table_s == nullptr || q.table_dp == nullptr || q.table_da == nullptr)
            throw std::invalid_argument("BatchPlan::preselect: every query needs its table rows");
        q.k = 1;
        check_search_args(db, q.audio, n, 1, query_allowed(q, allowed));
    }
    return n;
}

}  // namespace

void rank_sum_search_batch(const Kernels& kernels, const Database& db, std::vector<BatchQuery>& queries,
                           int64_t window, Preselect preselect, const AllowedSchedule& allowed, int threads,
                           BatchMethod method) {
    for (auto& q : queries) {
        if (q.has_allowed && allowed.per_step)
            throw std::invalid_argument(
                "allowed: expected either a schedule for every query or a bitset per query");
        check_search_args(db, q.audio, window, q.k, query_allowed(q, allowed));
        q.table_s = nullptr;
    }
    run_batch(kernels, db, queries, window, preselect, allowed, threads, method);
}

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
    method = resolve_method(impl_->kern, int64_t(queries.size()), threads, method);
    std::shared_ptr<const BlockedBatch> b;
    if (method == BatchMethod::Blocked) b = impl_->get(n, threads);
    run_batch(impl_->kern, impl_->db, queries, n, impl_->pre, allowed, threads, method, b.get());
}

int64_t BatchPlan::n_setups() const {
    std::lock_guard<std::mutex> lock(impl_->mutex);
    return int64_t(impl_->blocked.size());
}

}  // namespace gesturedb
