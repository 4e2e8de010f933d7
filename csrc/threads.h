// How many threads a call uses when it is not told: the CPUs this process may
// run on, not the CPUs the machine has (csrc/threads.cpp says why).
#pragma once

#include <string>

namespace gesturedb {

// Worker threads for a call that passes threads <= 0: the CPUs in this
// process's affinity mask, bounded by the cgroup CPU quota, at least 1.
// gesturedb.threads.available_cpus() applies the same rule in Python.
int default_threads();

// The CPU quota of the cgroup mounted at root ("/sys/fs/cgroup"), in whole CPUs
// rounded up, or 0 when there is none (no quota, no cgroup files, or files that
// do not parse). cgroup v2's cpu.max is read first, then v1's
// cpu/cpu.cfs_quota_us and cpu/cpu.cfs_period_us. Root is a parameter so tests
// can point it at fake files.
int cgroup_cpu_limit(const std::string& root);

}  // namespace gesturedb
