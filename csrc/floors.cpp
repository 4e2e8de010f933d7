// The benchmark's read floors (search.h: stream_sum_f32, gather_sum_f32):
// reads at memory bandwidth and at the step's scattered prefetch distance,
// the floors benchmarks/bench_search.py measures the step against.
#include "search.h"
#include "pool.h"
#include "prefetch.h"
#include "threads.h"

#include <algorithm>
#include <stdexcept>
#include <string>
#include <vector>

namespace gesturedb {
namespace {

// Adds p[0..len) to 16 independent float partial sums (so the adds stay off
// the critical path and a loop is bound by memory) and the last len % 16 to
// tail: the read of the benchmark's floors.
inline void accumulate16(const float* p, int64_t len, float (&acc)[16], double& tail) {
    int64_t i = 0;
    for (; i + 16 <= len; i += 16)
        for (int j = 0; j < 16; ++j) acc[j] += p[i + j];
    for (; i < len; ++i) tail += p[i];
}

}  // namespace

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

}  // namespace gesturedb
