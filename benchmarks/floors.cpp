// The read floors of benchmarks/bench_search.py: how fast the bytes a step
// must read can be read at all. Benchmark code, so it is not in gesturedb._core:
// benchmarks/floors.py compiles it on demand with the core's flags and calls it
// through ctypes (plain C entry points, no Python headers). It reads with the
// core's own pool and prefetch distance (csrc/pool.h, csrc/prefetch.h), so a
// floor moves with the step it bounds.
#include "pool.h"
#include "prefetch.h"
#include "threads.h"

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <exception>
#include <stdexcept>
#include <string>
#include <vector>

namespace gesturedb {
namespace {

// Adds p[0..len) to 16 independent float partial sums (so the adds stay off
// the critical path and a loop is bound by memory) and the last len % 16 to
// tail: the read of both floors.
inline void accumulate16(const float* p, int64_t len, float (&acc)[16], double& tail) {
    int64_t i = 0;
    for (; i + 16 <= len; i += 16)
        for (int j = 0; j < 16; ++j) acc[j] += p[i + j];
    for (; i < len; ++i) tail += p[i];
}

// Sum of n floats, read once in parallel: a streaming read at memory bandwidth,
// the floor against which the benchmark measures the step.
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

// Sum of the rows_each consecutive rows of a (rows, cols) matrix that start at
// each of starts[0..n), read in parallel with the step's prefetching: the
// latency-bound floor of a scattered pass (one audio window or one pose row per
// segment, as every exact step must read). Throws std::invalid_argument when a
// start reaches outside the matrix.
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
        auto prefetch = [&](int64_t i) {
            prefetch_bytes(data + starts[i] * cols, len * int64_t(sizeof(float)));
        };
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

// An exception's message into err (err_len bytes, always terminated).
void message(const std::exception& e, char* err, int64_t err_len) {
    if (err_len < 1) return;
    std::strncpy(err, e.what(), size_t(err_len - 1));
    err[err_len - 1] = '\0';
}

}  // namespace
}  // namespace gesturedb

// The C entry points floors.py calls: 0 on success with the sum in *out, or
// -1 with the message in err (no exception may cross into ctypes).
extern "C" {

int gesturedb_stream_sum_f32(const float* data, int64_t n, int threads, double* out, char* err,
                             int64_t err_len) {
    try {
        *out = gesturedb::stream_sum_f32(data, n, threads);
        return 0;
    } catch (const std::exception& e) {
        gesturedb::message(e, err, err_len);
        return -1;
    }
}

int gesturedb_gather_sum_f32(const float* data, int64_t rows, int64_t cols, const int64_t* starts, int64_t n,
                             int64_t rows_each, int threads, double* out, char* err, int64_t err_len) {
    try {
        *out = gesturedb::gather_sum_f32(data, rows, cols, starts, n, rows_each, threads);
        return 0;
    } catch (const std::exception& e) {
        gesturedb::message(e, err, err_len);
        return -1;
    }
}

}  // extern "C"
