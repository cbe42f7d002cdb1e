// ThreadSanitizer support for Debian's abseil (linked into every executable
// of the `tsan` preset only; CMake option FD_TSAN).
//
// Why: abseil's synchronization library is a Debian shared library built
// without -fsanitize=thread, so TSan never sees absl::Mutex, absl::CondVar or
// absl::Notification take or release anything (they use atomics and futexes
// inside the library) and reports every access guarded by them as a data
// race: a two-thread counter under absl::MutexLock is "racy" without this
// file. An abseil built with TSan annotates these operations itself
// (ABSL_TSAN_MUTEX_PRE_LOCK and friends in mutex.cc); this file adds the same
// annotations from outside.
//
// How: the executable defines the out-of-line members of those classes; ELF
// symbol interposition makes every caller (our code, and gRPC, which locks
// absl::Mutex too) call these definitions, which tell TSan what happens
// (<sanitizer/tsan_interface.h>) and call the library's own implementation
// found with dlsym(RTLD_NEXT). Accesses inside a real call (conditions that
// the library evaluates under the lock) are inside TSan's ignore region, as
// with an instrumented abseil.
#if !defined(__SANITIZE_THREAD__)
#error "tsan_absl_sync.cc is for -fsanitize=thread builds (GCC) only"
#endif

#include <dlfcn.h>
#include <sanitizer/tsan_interface.h>

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>

#include "absl/synchronization/mutex.h"
#include "absl/synchronization/notification.h"
#include "absl/time/time.h"

namespace {

// The mangled name of absl::<inline namespace>::<rest>, e.g.
// "_ZN4absl7debian35Mutex4LockEv" for rest "5Mutex4LockEv".
std::string AbslSymbol(const char* prefix, const char* rest) {
#define FD_STRINGIFY_INNER(x) #x
#define FD_STRINGIFY(x) FD_STRINGIFY_INNER(x)
  const std::string ns = FD_STRINGIFY(ABSL_OPTION_INLINE_NAMESPACE_NAME);
  return std::string(prefix) + "4absl" + std::to_string(ns.size()) + ns + rest;
}

// The library's definition of a member shadowed here.
template <typename Fn>
Fn Real(const char* prefix, const char* rest) {
  const std::string name = AbslSymbol(prefix, rest);
  void* symbol = dlsym(RTLD_NEXT, name.c_str());
  if (symbol == nullptr) {
    std::fprintf(stderr, "tsan_absl_sync: %s not found in abseil\n", name.c_str());
    std::abort();
  }
  Fn fn;
  static_assert(sizeof(fn) == sizeof(symbol));
  std::memcpy(&fn, &symbol, sizeof(fn));
  return fn;
}

// True for a call from outside abseil, false for one that an annotated call
// makes inside the library (AwaitWithTimeout calls AwaitWithDeadline,
// Notification::Notify locks its Mutex): only the outermost call tells TSan
// what happens, else a lock would be released or taken twice.
class OuterCall {
 public:
  OuterCall() : outer_(depth_++ == 0) {}
  ~OuterCall() { --depth_; }
  OuterCall(const OuterCall&) = delete;
  OuterCall& operator=(const OuterCall&) = delete;
  operator bool() const { return outer_; }  // NOLINT: reads as a condition

 private:
  static thread_local int depth_;
  const bool outer_;
};
thread_local int OuterCall::depth_ = 0;

// Whether `return_address` lies in one of Debian's gRPC libraries.
bool CalledFromGrpc(const void* return_address) {
  Dl_info info;
  if (dladdr(return_address, &info) == 0 || info.dli_fname == nullptr) return false;
  const char* base = std::strrchr(info.dli_fname, '/');
  base = base == nullptr ? info.dli_fname : base + 1;
  return std::strncmp(base, "libgrpc", 7) == 0 || std::strncmp(base, "libgpr", 6) == 0;
}

// A waiting call that releases `mu` and takes it back before returning:
// for TSan an unlock, the library's call (ignored), then a lock.
template <typename Call>
auto ReleaseAndRetake(bool outer, void* mu, unsigned flags, Call call) {
  if (outer) __tsan_mutex_pre_unlock(mu, flags);
  auto result = call();
  if (outer) {
    __tsan_mutex_post_unlock(mu, flags);
    __tsan_mutex_pre_lock(mu, flags);
    __tsan_mutex_post_lock(mu, flags, 0);
  }
  return result;
}

}  // namespace

namespace absl {
ABSL_NAMESPACE_BEGIN

// ---------------------------------------------------------------- Mutex

// A Mutex that gRPC destroys is not announced: gRPC frees its objects
// through reference counts in its own uninstrumented code, so TSan would see
// the last lock (announced below) but not the hand-off before the free, and
// report the destruction as a race. Its locks stay announced: they are the
// happens-before edges through which our data crosses gRPC's threads.
Mutex::~Mutex() {
  const OuterCall outer;
  using Fn = void (*)(Mutex*);
  static const Fn real = Real<Fn>("_ZN", "5MutexD2Ev");
  if (outer && !CalledFromGrpc(__builtin_return_address(0))) __tsan_mutex_destroy(this, 0);
  real(this);
}

void Mutex::Lock() {
  const OuterCall outer;
  using Fn = void (*)(Mutex*);
  static const Fn real = Real<Fn>("_ZN", "5Mutex4LockEv");
  if (outer) __tsan_mutex_pre_lock(this, 0);
  real(this);
  if (outer) __tsan_mutex_post_lock(this, 0, 0);
}

void Mutex::ReaderLock() {
  const OuterCall outer;
  using Fn = void (*)(Mutex*);
  static const Fn real = Real<Fn>("_ZN", "5Mutex10ReaderLockEv");
  if (outer) __tsan_mutex_pre_lock(this, __tsan_mutex_read_lock);
  real(this);
  if (outer) __tsan_mutex_post_lock(this, __tsan_mutex_read_lock, 0);
}

bool Mutex::TryLock() {
  const OuterCall outer;
  using Fn = bool (*)(Mutex*);
  static const Fn real = Real<Fn>("_ZN", "5Mutex7TryLockEv");
  if (outer) __tsan_mutex_pre_lock(this, __tsan_mutex_try_lock);
  const bool locked = real(this);
  if (outer)
    __tsan_mutex_post_lock(this, locked ? __tsan_mutex_try_lock : __tsan_mutex_try_lock_failed, 0);
  return locked;
}

bool Mutex::ReaderTryLock() {
  const OuterCall outer;
  using Fn = bool (*)(Mutex*);
  static const Fn real = Real<Fn>("_ZN", "5Mutex13ReaderTryLockEv");
  const unsigned flags = __tsan_mutex_read_lock | __tsan_mutex_try_lock;
  if (outer) __tsan_mutex_pre_lock(this, flags);
  const bool locked = real(this);
  if (outer)
    __tsan_mutex_post_lock(
        this, locked ? flags : (__tsan_mutex_read_lock | __tsan_mutex_try_lock_failed), 0);
  return locked;
}

void Mutex::Unlock() {
  const OuterCall outer;
  using Fn = void (*)(Mutex*);
  static const Fn real = Real<Fn>("_ZN", "5Mutex6UnlockEv");
  if (outer) __tsan_mutex_pre_unlock(this, 0);
  real(this);
  if (outer) __tsan_mutex_post_unlock(this, 0);
}

void Mutex::ReaderUnlock() {
  const OuterCall outer;
  using Fn = void (*)(Mutex*);
  static const Fn real = Real<Fn>("_ZN", "5Mutex12ReaderUnlockEv");
  if (outer) __tsan_mutex_pre_unlock(this, __tsan_mutex_read_lock);
  real(this);
  if (outer) __tsan_mutex_post_unlock(this, __tsan_mutex_read_lock);
}

void Mutex::LockWhen(const Condition& cond) {
  const OuterCall outer;
  using Fn = void (*)(Mutex*, const Condition&);
  static const Fn real = Real<Fn>("_ZN", "5Mutex8LockWhenERKNS0_9ConditionE");
  if (outer) __tsan_mutex_pre_lock(this, 0);
  real(this, cond);
  if (outer) __tsan_mutex_post_lock(this, 0, 0);
}

void Mutex::ReaderLockWhen(const Condition& cond) {
  const OuterCall outer;
  using Fn = void (*)(Mutex*, const Condition&);
  static const Fn real = Real<Fn>("_ZN", "5Mutex14ReaderLockWhenERKNS0_9ConditionE");
  if (outer) __tsan_mutex_pre_lock(this, __tsan_mutex_read_lock);
  real(this, cond);
  if (outer) __tsan_mutex_post_lock(this, __tsan_mutex_read_lock, 0);
}

// The timed forms hold the lock on return whatever the condition's outcome.
bool Mutex::LockWhenWithTimeout(const Condition& cond, Duration timeout) {
  const OuterCall outer;
  using Fn = bool (*)(Mutex*, const Condition&, Duration);
  static const Fn real =
      Real<Fn>("_ZN", "5Mutex19LockWhenWithTimeoutERKNS0_9ConditionENS0_8DurationE");
  if (outer) __tsan_mutex_pre_lock(this, 0);
  const bool met = real(this, cond, timeout);
  if (outer) __tsan_mutex_post_lock(this, 0, 0);
  return met;
}

bool Mutex::LockWhenWithDeadline(const Condition& cond, Time deadline) {
  const OuterCall outer;
  using Fn = bool (*)(Mutex*, const Condition&, Time);
  static const Fn real =
      Real<Fn>("_ZN", "5Mutex20LockWhenWithDeadlineERKNS0_9ConditionENS0_4TimeE");
  if (outer) __tsan_mutex_pre_lock(this, 0);
  const bool met = real(this, cond, deadline);
  if (outer) __tsan_mutex_post_lock(this, 0, 0);
  return met;
}

bool Mutex::ReaderLockWhenWithTimeout(const Condition& cond, Duration timeout) {
  const OuterCall outer;
  using Fn = bool (*)(Mutex*, const Condition&, Duration);
  static const Fn real =
      Real<Fn>("_ZN", "5Mutex25ReaderLockWhenWithTimeoutERKNS0_9ConditionENS0_8DurationE");
  if (outer) __tsan_mutex_pre_lock(this, __tsan_mutex_read_lock);
  const bool met = real(this, cond, timeout);
  if (outer) __tsan_mutex_post_lock(this, __tsan_mutex_read_lock, 0);
  return met;
}

bool Mutex::ReaderLockWhenWithDeadline(const Condition& cond, Time deadline) {
  const OuterCall outer;
  using Fn = bool (*)(Mutex*, const Condition&, Time);
  static const Fn real =
      Real<Fn>("_ZN", "5Mutex26ReaderLockWhenWithDeadlineERKNS0_9ConditionENS0_4TimeE");
  if (outer) __tsan_mutex_pre_lock(this, __tsan_mutex_read_lock);
  const bool met = real(this, cond, deadline);
  if (outer) __tsan_mutex_post_lock(this, __tsan_mutex_read_lock, 0);
  return met;
}

// Await* run under a writer lock in this project (a reader lock held across
// Await would be reported as a bad unlock: an abseil built with TSan keeps
// the holder's mode, this shim cannot see it).
void Mutex::Await(const Condition& cond) {
  const OuterCall outer;
  using Fn = void (*)(Mutex*, const Condition&);
  static const Fn real = Real<Fn>("_ZN", "5Mutex5AwaitERKNS0_9ConditionE");
  ReleaseAndRetake(outer, this, 0, [&] {
    real(this, cond);
    return 0;
  });
}

bool Mutex::AwaitWithTimeout(const Condition& cond, Duration timeout) {
  const OuterCall outer;
  using Fn = bool (*)(Mutex*, const Condition&, Duration);
  static const Fn real =
      Real<Fn>("_ZN", "5Mutex16AwaitWithTimeoutERKNS0_9ConditionENS0_8DurationE");
  return ReleaseAndRetake(outer, this, 0, [&] { return real(this, cond, timeout); });
}

bool Mutex::AwaitWithDeadline(const Condition& cond, Time deadline) {
  const OuterCall outer;
  using Fn = bool (*)(Mutex*, const Condition&, Time);
  static const Fn real = Real<Fn>("_ZN", "5Mutex17AwaitWithDeadlineERKNS0_9ConditionENS0_4TimeE");
  return ReleaseAndRetake(outer, this, 0, [&] { return real(this, cond, deadline); });
}

// ---------------------------------------------------------------- CondVar

void CondVar::Wait(Mutex* mu) {
  const OuterCall outer;
  using Fn = void (*)(CondVar*, Mutex*);
  static const Fn real = Real<Fn>("_ZN", "7CondVar4WaitEPNS0_5MutexE");
  ReleaseAndRetake(outer, mu, 0, [&] {
    real(this, mu);
    return 0;
  });
}

bool CondVar::WaitWithTimeout(Mutex* mu, Duration timeout) {
  const OuterCall outer;
  using Fn = bool (*)(CondVar*, Mutex*, Duration);
  static const Fn real = Real<Fn>("_ZN", "7CondVar15WaitWithTimeoutEPNS0_5MutexENS0_8DurationE");
  return ReleaseAndRetake(outer, mu, 0, [&] { return real(this, mu, timeout); });
}

bool CondVar::WaitWithDeadline(Mutex* mu, Time deadline) {
  const OuterCall outer;
  using Fn = bool (*)(CondVar*, Mutex*, Time);
  static const Fn real = Real<Fn>("_ZN", "7CondVar16WaitWithDeadlineEPNS0_5MutexENS0_4TimeE");
  return ReleaseAndRetake(outer, mu, 0, [&] { return real(this, mu, deadline); });
}

// ---------------------------------------------------------------- Notification

// Notify happens before every wait that sees it.
void Notification::Notify() {
  const OuterCall outer;
  using Fn = void (*)(Notification*);
  static const Fn real = Real<Fn>("_ZN", "12Notification6NotifyEv");
  if (outer) __tsan_release(this);
  real(this);
}

void Notification::WaitForNotification() const {
  const OuterCall outer;
  using Fn = void (*)(const Notification*);
  static const Fn real = Real<Fn>("_ZNK", "12Notification19WaitForNotificationEv");
  real(this);
  if (outer) __tsan_acquire(const_cast<Notification*>(this));
}

bool Notification::WaitForNotificationWithTimeout(Duration timeout) const {
  const OuterCall outer;
  using Fn = bool (*)(const Notification*, Duration);
  static const Fn real =
      Real<Fn>("_ZNK", "12Notification30WaitForNotificationWithTimeoutENS0_8DurationE");
  const bool notified = real(this, timeout);
  if (outer && notified) __tsan_acquire(const_cast<Notification*>(this));
  return notified;
}

bool Notification::WaitForNotificationWithDeadline(Time deadline) const {
  const OuterCall outer;
  using Fn = bool (*)(const Notification*, Time);
  static const Fn real =
      Real<Fn>("_ZNK", "12Notification31WaitForNotificationWithDeadlineENS0_4TimeE");
  const bool notified = real(this, deadline);
  if (outer && notified) __tsan_acquire(const_cast<Notification*>(this));
  return notified;
}

ABSL_NAMESPACE_END
}  // namespace absl
