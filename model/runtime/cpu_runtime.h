// Process-wide settings for LibTorch CPU inference, applied at the top of
// main() by framediffuser-server and the benchmarks.
//
// malloc: LibTorch's CPU allocator takes every tensor from malloc. With glibc's
// defaults, blocks above the (dynamic) mmap threshold are mmap'ed and
// unmapped on every allocation, and the heap top is trimmed back to the
// system as soon as 128 KiB are free; a denoising step allocates and frees
// the same large activations again and again, so each step page-faults its
// whole working set anew. On the golden config-B step that was ~640k minor
// faults per 36 steps and most of the benchmark's system time
// (docs/BENCHMARKS.md, "Model (CPU)").
#ifndef FD_MODEL_RUNTIME_CPU_RUNTIME_H_
#define FD_MODEL_RUNTIME_CPU_RUNTIME_H_

#include <string>
#include <utility>
#include <vector>

namespace fd::model {

// Keeps freed memory in the process for reuse: mmap only for blocks above
// 32 MiB (glibc's maximum) and never trim the heap top. The resident set then
// stays at its high-water mark instead of shrinking between frames, which is
// what a server running the same shapes frame after frame wants. A setting
// the user made through glibc's environment variables (MALLOC_MMAP_THRESHOLD_,
// MALLOC_TRIM_THRESHOLD_, GLIBC_TUNABLES) is left alone. Call once, early in
// main, before worker threads start. Returns a one-line description of what
// it did (for the startup log). Thread-safety: not thread-safe. No-op where
// the C library is not glibc.
std::string TuneMallocForInference();

// How idle OpenMP threads wait: the threading policy under which a second
// intra-op thread never makes a frame slower (docs/BENCHMARKS.md,
// "Threading policy").
//  * Spinning without bound (OMP_WAIT_POLICY=ACTIVE) steals the cores other
//    threads need: on a 2-core machine the served frame rate fell to
//    0.3-0.6x of the same frames in-process.
//  * Sleeping at once (PASSIVE alone) makes every small OpenMP region wake a
//    sleeping thread: a config-B step at 2 threads took 96-147 ms against
//    28-42 ms at 1 thread.
//  * PASSIVE with GOMP_SPINCOUNT=kOpenMpSpinCount: a worker spins about
//    3 ms (libgomp's estimate: 100000 spins per ms) for the next region,
//    then sleeps; and libgomp spins not at all while it manages more threads
//    than there are CPUs (its "throttled" count is 0 under PASSIVE), so
//    oversubscription (workers x threads > cores) degrades to PASSIVE
//    instead of to ACTIVE's contention.
// libgomp reads both variables when it is loaded, before main, so this
// re-executes the program once (/proc/self/exe, same argv) with the two set.
// A user's own OMP_WAIT_POLICY or GOMP_SPINCOUNT is respected: nothing is
// added then, and no re-exec happens. Returns only if no re-exec happened.
// Call first thing in main. Thread-safety: before any thread starts.
inline constexpr char kOpenMpSpinCount[] = "300000";
void UseBoundedOpenMpSpin(char** argv);

// The variables UseBoundedOpenMpSpin adds to the current environment
// (name, value), or none when the user set either. Pure, for tests and logs.
std::vector<std::pair<std::string, std::string>> BoundedOpenMpSpinSettings();

// "OMP_WAIT_POLICY=PASSIVE GOMP_SPINCOUNT=300000" as the process runs
// (unset ones omitted; "" when neither is set), for the startup log.
std::string DescribeOpenMpWaiting();

// BLAS calls (LibTorch's Linear layers, matmuls) run on the calling thread.
// Debian's LibTorch links the pthread build of OpenBLAS, which keeps its own
// pool of one thread per core beside LibTorch's OpenMP threads and the
// scheduler workers: its idle threads spin in sched_yield (on the config-B
// step half the process's CPU time was system time), and concurrent callers
// (two scheduler workers) queue for the one pool. With one BLAS thread the
// config-B step took 33 ms instead of 50-54 ms (docs/BENCHMARKS.md); the
// parallelism comes from LibTorch's threads and the scheduler workers. An
// explicit OPENBLAS_NUM_THREADS or GOTO_NUM_THREADS is respected. The
// OpenBLAS entry point is looked up at run time, so another BLAS is left
// alone. Returns a one-line description for the startup log. Thread-safety:
// call once, early in main, before BLAS is used from several threads.
std::string UseSingleThreadedBlas();

}  // namespace fd::model

#endif  // FD_MODEL_RUNTIME_CPU_RUNTIME_H_
