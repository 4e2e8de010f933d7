// Non-owning views over caller-owned memory (numpy arrays on the Python side).
//
// Every signature in the core takes one of these instead of a bare pointer so
// the shape and the ownership are visible where the function is declared: a
// view never frees, never outlives the array it came from, and is only ever
// built in bindings.cpp (from a checked numpy array) or in tests.
#pragma once

#include <cstddef>
#include <cstdint>

namespace gesturedb {

// A contiguous run of `size` values.
template <class T>
struct Span1 {
    T* data = nullptr;
    int64_t size = 0;

    T& operator[](int64_t i) const { return data[i]; }
    T* begin() const { return data; }
    T* end() const { return data + size; }
};

// A C-contiguous (row-major) matrix: row i starts at data + i * cols.
template <class T>
struct Span2 {
    T* data = nullptr;
    int64_t rows = 0;
    int64_t cols = 0;

    T* row(int64_t i) const { return data + i * cols; }
    T& operator()(int64_t i, int64_t j) const { return data[i * cols + j]; }
};

// A packed bitset over database frames: bit (f & 63) of word (f >> 6).
// An empty view (words == nullptr) means "every frame allowed".
struct BitsetView {
    const uint64_t* words = nullptr;
    int64_t n_words = 0;

    bool all() const { return words == nullptr; }
    bool test(int64_t f) const { return words == nullptr || ((words[f >> 6] >> (f & 63)) & 1u) != 0; }
};

}  // namespace gesturedb
