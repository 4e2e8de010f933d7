// Picks the kernel table once: what the CPU can execute (cpuid), what the OS
// saves on a context switch (xgetbv), then the GESTUREDB_SIMD override.
//
// Both checks are needed: a CPU may report AVX-512 while the OS (or a
// hypervisor) does not enable the ZMM state, and executing the instructions
// then faults.
#include "kernels.h"

#include <atomic>
#include <cstdlib>
#include <cstring>
#include <stdexcept>
#include <string>

#ifdef GESTUREDB_X86
#include <cpuid.h>
#endif

namespace gesturedb {
namespace {

const Kernels kScalar{"scalar",
                      l2sq_rows_f32_scalar,
                      cosdots_f32_scalar,
                      dots_block_f32_scalar,
                      l2filter_f32_scalar,
                      cosfilter_f32_scalar,
                      l2sq_rows_f16_scalar,
                      l2sq_blocks_f32_scalar,
                      l2sq_blocks_f16_scalar,
                      l2sq_pairs_f32_scalar,
                      cosdots_pairs_f32_scalar,
                      projfilter_f32_scalar,
                      projkeep_f32_scalar};
#ifdef GESTUREDB_X86
const Kernels kAvx2{"avx2",
                    l2sq_rows_f32_avx2,
                    cosdots_f32_avx2,
                    dots_block_f32_avx2,
                    l2filter_f32_avx2,
                    cosfilter_f32_avx2,
                    l2sq_rows_f16_avx2,
                    l2sq_blocks_f32_avx2,
                    l2sq_blocks_f16_avx2,
                    l2sq_pairs_f32_avx2,
                    cosdots_pairs_f32_avx2,
                    projfilter_f32_avx2,
                    projkeep_f32_avx2};
const Kernels kAvx512{"avx512",
                      l2sq_rows_f32_avx512,
                      cosdots_f32_avx512,
                      dots_block_f32_avx512,
                      l2filter_f32_avx512,
                      cosfilter_f32_avx512,
                      l2sq_rows_f16_avx512,
                      l2sq_blocks_f32_avx512,
                      l2sq_blocks_f16_avx512,
                      l2sq_pairs_f32_avx512,
                      cosdots_pairs_f32_avx512,
                      projfilter_f32_avx512,
                      projkeep_f32_avx512};
#endif

struct CpuSupport {
    bool avx2 = false;
    bool avx512 = false;
};

#ifdef GESTUREDB_X86
uint64_t read_xcr0() {
    uint32_t lo = 0, hi = 0;
    // xgetbv with ecx = 0 reads XCR0; only valid once cpuid reported OSXSAVE
    __asm__ volatile("xgetbv" : "=a"(lo), "=d"(hi) : "c"(0));
    return (uint64_t(hi) << 32) | lo;
}
#endif

CpuSupport detect() {
    CpuSupport s;
#ifdef GESTUREDB_X86
    unsigned a = 0, b = 0, c = 0, d = 0;
    if (!__get_cpuid(1, &a, &b, &c, &d)) return s;
    const bool osxsave = (c >> 27) & 1, avx = (c >> 28) & 1, fma = (c >> 12) & 1;
    const bool f16c = (c >> 29) & 1;  // half-precision conversions, used by the pose filter
    if (!osxsave || !avx) return s;
    const uint64_t xcr0 = read_xcr0();
    const bool ymm_saved = (xcr0 & 0x6) == 0x6;    // SSE + AVX state
    const bool zmm_saved = (xcr0 & 0xE6) == 0xE6;  // + opmask, ZMM_Hi256, Hi16_ZMM
    if (!__get_cpuid_count(7, 0, &a, &b, &c, &d)) return s;
    const bool avx2 = (b >> 5) & 1;
    const bool f = (b >> 16) & 1, dq = (b >> 17) & 1, bw = (b >> 30) & 1, vl = (b >> 31) & 1;
    s.avx2 = ymm_saved && avx2 && fma && f16c;
    s.avx512 = s.avx2 && zmm_saved && f && dq && bw && vl;
#endif
    return s;
}

const CpuSupport& cpu() {
    static const CpuSupport s = detect();
    return s;
}

const Kernels* lookup(const char* isa) {
    if (std::strcmp(isa, "scalar") == 0) return &kScalar;
#ifdef GESTUREDB_X86
    if (std::strcmp(isa, "avx2") == 0) return cpu().avx2 ? &kAvx2 : nullptr;
    if (std::strcmp(isa, "avx512") == 0) return cpu().avx512 ? &kAvx512 : nullptr;
#endif
    return nullptr;
}

std::string available_list() {
    const char* names[8];
    const int n = available_isas(names, 8);
    std::string out;
    for (int i = 0; i < n; ++i) {
        if (i) out += ", ";
        out += names[i];
    }
    return out;
}

const Kernels* initial_table() {
    const char* env = std::getenv("GESTUREDB_SIMD");
    if (env != nullptr && *env != '\0') {
        const Kernels* k = lookup(env);
        if (k == nullptr) {
            throw std::invalid_argument(std::string("GESTUREDB_SIMD: expected one of ") + available_list() +
                                        " on this CPU; got '" + env + "'");
        }
        return k;
    }
#ifdef GESTUREDB_X86
    if (cpu().avx512) return &kAvx512;
    if (cpu().avx2) return &kAvx2;
#endif
    return &kScalar;
}

std::atomic<const Kernels*>& active_slot() {
    // initialised on first use (module import calls active_kernels() once so a
    // bad GESTUREDB_SIMD fails the import, not the first search)
    static std::atomic<const Kernels*> slot{initial_table()};
    return slot;
}

}  // namespace

int available_isas(const char** names, int capacity) {
    int n = 0;
    auto add = [&](const char* s) {
        if (n < capacity) names[n] = s;
        ++n;
    };
    add("scalar");
#ifdef GESTUREDB_X86
    if (cpu().avx2) add("avx2");
    if (cpu().avx512) add("avx512");
#endif
    return n;
}

const Kernels& kernels_for(const char* isa) {
    const Kernels* k = lookup(isa);
    if (k == nullptr) {
        throw std::invalid_argument(std::string("simd: expected one of ") + available_list() +
                                    " on this CPU; got '" + isa + "'");
    }
    return *k;
}

const Kernels& active_kernels() { return *active_slot().load(std::memory_order_acquire); }

void set_simd(const char* isa) { active_slot().store(&kernels_for(isa), std::memory_order_release); }

}  // namespace gesturedb
