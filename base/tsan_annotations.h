// Happens-before edges for ThreadSanitizer that it cannot see itself
// (nothing outside a TSan build: the macros expand to no code).
//
// Why: Debian's gRPC is not built with TSan, so a hand-off that happens
// inside libgrpc (an operation started on one thread, its reaction run on a
// completion-queue thread) is invisible to it. An object created on the
// first thread and first touched in the reaction is then reported as racing
// with its own allocation. FD_TSAN_RELEASE(addr) once the object is built
// and FD_TSAN_ACQUIRE(addr) at the start of each reaction state the order
// that gRPC guarantees (a reaction follows the start of its operation).
#ifndef FD_BASE_TSAN_ANNOTATIONS_H_
#define FD_BASE_TSAN_ANNOTATIONS_H_

#if defined(__SANITIZE_THREAD__)
#define FD_TSAN_ENABLED 1
#elif defined(__has_feature)
#if __has_feature(thread_sanitizer)
#define FD_TSAN_ENABLED 1
#endif
#endif

#if defined(FD_TSAN_ENABLED)
#include <sanitizer/tsan_interface.h>
#define FD_TSAN_RELEASE(addr) __tsan_release(static_cast<void*>(addr))
#define FD_TSAN_ACQUIRE(addr) __tsan_acquire(static_cast<void*>(addr))
#else
#define FD_TSAN_RELEASE(addr) static_cast<void>(0)
#define FD_TSAN_ACQUIRE(addr) static_cast<void>(0)
#endif

#endif  // FD_BASE_TSAN_ANNOTATIONS_H_
