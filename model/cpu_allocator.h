// Process-wide tuning of glibc malloc for LibTorch CPU inference.
//
// LibTorch's CPU allocator takes every tensor from malloc. With glibc's
// defaults, blocks above the (dynamic) mmap threshold are mmap'ed and
// unmapped on every allocation, and the heap top is trimmed back to the
// system as soon as 128 KiB are free; a denoising step allocates and frees
// the same large activations again and again, so each step page-faults its
// whole working set anew. On the golden config-B step that was ~640k minor
// faults per 36 steps and most of the benchmark's system time
// (docs/BENCHMARKS.md, "Model (CPU)").
#ifndef FD_MODEL_CPU_ALLOCATOR_H_
#define FD_MODEL_CPU_ALLOCATOR_H_

#include <string>

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

}  // namespace fd::model

#endif  // FD_MODEL_CPU_ALLOCATOR_H_
