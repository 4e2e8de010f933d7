// The default thread count. std::thread::hardware_concurrency() counts the
// machine's CPUs; a process started under `taskset`, a batch scheduler's CPU
// set or a container's CPU quota may use fewer, and a pool sized by the
// machine then runs several threads per CPU: each waits for the others at
// every barrier of a step, and the step takes longer than with one thread per
// CPU. So the count is what the process may actually use: its affinity mask,
// bounded by the cgroup quota (the rule Go 1.25 and the JVM apply).
#include "threads.h"

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <thread>
#include <vector>

#ifdef __linux__
#include <sched.h>
#endif

namespace gesturedb {
namespace {

// The whitespace-separated words in the first 4 KiB of a file (none when it
// cannot be read): what gesturedb.threads reads, so the two agree on any file.
std::vector<std::string> read_words(const std::string& path) {
    std::vector<std::string> words;
    std::FILE* f = std::fopen(path.c_str(), "rb");
    if (f == nullptr) return words;
    char buf[4096];
    const size_t n = std::fread(buf, 1, sizeof buf, f);
    std::fclose(f);
    std::string word;
    for (size_t i = 0; i <= n; ++i) {
        if (i < n && !std::isspace(static_cast<unsigned char>(buf[i]))) {
            word += buf[i];
        } else if (!word.empty()) {
            words.push_back(word);
            word.clear();
        }
    }
    return words;
}

// A whole non-negative decimal number, or -1 (a quota of "-1" means none in
// cgroup v1, so it need not parse as a number here).
long long parse_count(const std::string& s) {
    if (s.empty() || s.size() > 18 || s.find_first_not_of("0123456789") != std::string::npos) return -1;
    return std::strtoll(s.c_str(), nullptr, 10);
}

// ceil(quota / period) in whole CPUs, or 0 when either is not a positive number.
int quota_cpus(const std::string& quota, const std::string& period) {
    const long long q = parse_count(quota), p = parse_count(period);
    if (q <= 0 || p <= 0) return 0;
    // a quota of 1.5 periods still lets two threads run half the time each:
    // rounding up keeps a second thread rather than leaving half a CPU unused
    const long long n = (q + p - 1) / p;
    return int(std::min<long long>(n, 1 << 20));
}

#ifdef __linux__
// CPUs in this process's affinity mask, or 0 when it cannot be read.
int affinity_cpus() {
    // a cpu_set_t holds 1024 CPUs and sched_getaffinity fails with EINVAL when
    // the kernel's mask is wider: grow the set until it fits (starting from
    // hardware_concurrency() instead would read a /sys file on every call)
    for (int n = CPU_SETSIZE; n <= (1 << 22); n *= 2) {
        cpu_set_t* set = CPU_ALLOC(n);
        if (set == nullptr) return 0;
        const size_t size = CPU_ALLOC_SIZE(n);
        CPU_ZERO_S(size, set);
        const int rc = sched_getaffinity(0, size, set);
        const int err = errno;
        const int count = rc == 0 ? CPU_COUNT_S(size, set) : 0;
        CPU_FREE(set);
        if (rc == 0) return count;
        if (err != EINVAL) return 0;
    }
    return 0;
}
#endif

}  // namespace

int cgroup_cpu_limit(const std::string& root) {
    // cgroup v2: one file, "max 100000" (no quota) or "200000 100000"
    const std::vector<std::string> v2 = read_words(root + "/cpu.max");
    if (v2.size() >= 2) return v2[0] == "max" ? 0 : quota_cpus(v2[0], v2[1]);
    // cgroup v1: two files, a quota of -1 meaning none
    const std::vector<std::string> quota = read_words(root + "/cpu/cpu.cfs_quota_us");
    const std::vector<std::string> period = read_words(root + "/cpu/cpu.cfs_period_us");
    if (quota.empty() || period.empty()) return 0;
    return quota_cpus(quota[0], period[0]);
}

int default_threads() {
    int n = 0;
#ifdef __linux__
    n = affinity_cpus();
#endif
    // elsewhere, or when the mask cannot be read, the machine's count is all that is known
    if (n <= 0) n = int(std::thread::hardware_concurrency());
    // inside a container the cgroup namespace shows the container's own cgroup
    // at /sys/fs/cgroup, so the fixed path reads the quota that applies here;
    // where there are no such files there is no bound. Read once: opening the
    // cgroup files took 30 us (2-core test machine), and this runs on every
    // search that does not say how many threads; a quota is set when a
    // container starts and rarely changes after. The affinity mask is read
    // every time (1 us), as `taskset -p` may change it while a process runs.
    static const int quota = cgroup_cpu_limit("/sys/fs/cgroup");
    if (quota > 0) n = std::min(n, quota);
    return std::max(n, 1);
}

}  // namespace gesturedb
