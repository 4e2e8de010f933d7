// The core's one thread pool: parallel_for, hnswlib's ParallelFor pattern.
// Every parallel pass of the search (a step's segment chunks, a batch's blocks
// of queries, the blocked set-up's per-frame passes) and the benchmark's read
// floors go through it, so one level of parallelism holds everywhere.
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <exception>
#include <mutex>
#include <system_error>
#include <thread>
#include <vector>

namespace gesturedb {

// Tasks are handed out through an atomic counter; the first exception is
// kept, the other workers stop taking tasks, and it is rethrown on the calling
// thread after every worker joined.
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

}  // namespace gesturedb
