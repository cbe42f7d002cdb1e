// The real framediffuser-server binary as a child process of the soak
// program (bench/soak.cc), so that its resident set, threads and open file
// descriptors are measured apart from the load generator's.
//
// The child's stderr (its JSON log) is read line by line on a thread: the
// bound port comes from the "listening on port N" line (--listen
// 127.0.0.1:0), events are counted, the last lines are kept for error
// reports, and waiting for an event is a condition wait on that reader, not a
// sleep. The child gets SIGKILL if this process dies first (PDEATHSIG).
#ifndef FD_BENCH_SOAK_SERVER_PROCESS_H_
#define FD_BENCH_SOAK_SERVER_PROCESS_H_

#include <sys/types.h>

#include <cstdint>
#include <deque>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"

namespace fd::bench {

// One look at a process in /proc.
struct ProcessSample {
  int64_t rss_kib = 0;  // VmRSS
  int64_t hwm_kib = 0;  // VmHWM: the peak resident set so far
  int threads = 0;      // Threads
  // Of those, gRPC core's executor threads ("default-executor"): a pool that
  // grows on demand to 2 x cores and never shrinks (grpc's executor.cc), so a
  // busier phase may add some without anything leaking.
  int grpc_executor_threads = 0;
  // gRPC core's timer threads ("grpc_global_timer"): it starts another when
  // none is waiting for the next timer (e.g. while callbacks run long) and
  // lets the extra ones go only when they wake, which an idle server may
  // not do for a long time.
  int grpc_timer_threads = 0;
  int fds = 0;  // entries of /proc/<pid>/fd
};

// Reads /proc/<pid>/status and /proc/<pid>/fd. INTERNAL if they cannot be
// read (the process is gone, or belongs to another user).
absl::StatusOr<ProcessSample> SampleProcess(pid_t pid);

// The names of a process's threads (/proc/<pid>/task/*/comm) with how many
// have each, e.g. "grpcpp_sync_ser x2, soak-worker"; for leak reports.
std::string ThreadNames(pid_t pid);

// Thread-safety: every method is thread-safe.
class ServerProcess {
 public:
  // Starts `binary` with `args` (stdin and stdout /dev/null, stderr read
  // here; every line is also appended to `log_path` unless it is empty) and
  // waits up to `timeout` for its listening line. The error says why, with
  // the log's last lines, if it exits or times out first.
  static absl::StatusOr<std::unique_ptr<ServerProcess>> Start(const std::string& binary,
                                                              const std::vector<std::string>& args,
                                                              const std::string& log_path,
                                                              absl::Duration timeout);
  // Kills the child (SIGKILL) if it still runs, and reaps it.
  ~ServerProcess();
  ServerProcess(const ServerProcess&) = delete;
  ServerProcess& operator=(const ServerProcess&) = delete;

  pid_t pid() const { return pid_; }
  int port() const ABSL_LOCKS_EXCLUDED(mu_);

  // Waits until `count` log lines with "event":"<event>" have arrived, or the
  // log ended, or `timeout` passed; returns whether they arrived.
  bool WaitForEvent(absl::string_view event, int count, absl::Duration timeout)
      ABSL_LOCKS_EXCLUDED(mu_);
  int EventCount(absl::string_view event) const ABSL_LOCKS_EXCLUDED(mu_);
  // Lines at level "warning" or "error" so far.
  int WarningCount() const ABSL_LOCKS_EXCLUDED(mu_);
  int ErrorCount() const ABSL_LOCKS_EXCLUDED(mu_);
  // The last `lines` lines of the log (at most 200 are kept), oldest first,
  // joined by "\n".
  std::string Tail(int lines) const ABSL_LOCKS_EXCLUDED(mu_);

  // SIGTERM (the server drains), then waits up to `timeout` for the log to
  // end and reaps the child; SIGKILL after the timeout. Returns the exit
  // status as a shell shows it (128 + signal for a signal).
  absl::StatusOr<int> Terminate(absl::Duration timeout) ABSL_LOCKS_EXCLUDED(mu_);

 private:
  ServerProcess(pid_t pid, int stderr_fd, int log_fd);
  void ReadLoop();
  void OnLineLocked(std::string line) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);

  const pid_t pid_;
  const int stderr_fd_;
  const int log_fd_;  // -1: no copy of the log
  std::thread reader_;

  mutable absl::Mutex mu_;
  std::optional<int> port_ ABSL_GUARDED_BY(mu_);
  bool eof_ ABSL_GUARDED_BY(mu_) = false;
  std::optional<int> exit_status_ ABSL_GUARDED_BY(mu_);  // once reaped
  std::map<std::string, int, std::less<>> events_ ABSL_GUARDED_BY(mu_);
  int warnings_ ABSL_GUARDED_BY(mu_) = 0;
  int errors_ ABSL_GUARDED_BY(mu_) = 0;
  std::deque<std::string> tail_ ABSL_GUARDED_BY(mu_);
};

}  // namespace fd::bench

#endif  // FD_BENCH_SOAK_SERVER_PROCESS_H_
