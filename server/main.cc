// framediffuser-server: serves FrameDiffuser environments over gRPC.
//
//   framediffuser-server --listen 0.0.0.0:50051 --model_repository /models
//       --metrics_listen 0.0.0.0:9464
//
// Signals: SIGTERM / SIGINT drain gracefully (exit 0 within --drain_timeout
// plus the frames in flight); SIGHUP rescans the model repository. Every
// option: --help.
#include <errno.h>
#include <fcntl.h>
#include <pthread.h>
#include <signal.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <string>
#include <thread>

#include "absl/strings/str_cat.h"
#include "server/log.h"
#include "server/server.h"
#include "server/server_config.h"
#include "session/compute_runtime.h"

namespace {

// Signals reach the main loop through a pipe. The server's own threads
// start with SIGTERM/SIGINT/SIGHUP blocked (they inherit main's mask), but
// threads that libraries start before main() (e.g. OpenBLAS's worker) do
// not block them: a signal the kernel hands to one of those while the main
// thread is busy (say, with the SIGHUP before it) would otherwise take the
// default action and kill the process without a drain. Whichever thread
// runs the handler, the signal number goes down the pipe.
int g_signal_pipe[2] = {-1, -1};

extern "C" void ForwardSignal(int signo) {
  const unsigned char byte = static_cast<unsigned char>(signo);
  const ssize_t written = write(g_signal_pipe[1], &byte, 1);  // async-signal-safe
  (void)written;
}

// The next forwarded signal (blocks; retries on EINTR).
int NextSignal() {
  for (;;) {
    unsigned char byte = 0;
    const ssize_t got = read(g_signal_pipe[0], &byte, 1);
    if (got == 1) return byte;
    if (got < 0 && errno != EINTR) return SIGTERM;  // the pipe broke: stop cleanly
  }
}

int Fail(const absl::Status& status) {
  std::cerr << "framediffuser-server: " << status.message() << "\n"
            << "(--help lists every option)\n";
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  using fd::server::LogEvent;
  fd::session::UseBoundedOpenMpSpin(argv);  // may re-execute the server
  absl::StatusOr<fd::server::ParsedCommandLine> parsed = fd::server::ParseCommandLine(argc, argv);
  if (!parsed.ok()) return Fail(parsed.status());
  if (parsed->help) {
    std::cout << fd::server::UsageText();
    return 0;
  }
  const fd::server::ServerConfig& config = parsed->config;
  absl::StatusOr<fd::server::LogFormat> format = fd::server::ParseLogFormat(config.log_format);
  if (!format.ok()) return Fail(format.status());
  fd::server::SetLogFormat(*format);

  // Before any thread starts: keep freed activations for the next frame
  // instead of page-faulting them in again (model/runtime/cpu_runtime.h).
  const std::string malloc_tuning = fd::session::TuneMallocForInference();
  const std::string blas_threads = fd::session::UseSingleThreadedBlas();
  LogEvent("process_tuning", {{"malloc", malloc_tuning},
                              {"blas", blas_threads},
                              {"openmp", fd::session::DescribeOpenMpWaiting()},
                              {"attention", fd::session::DescribeFusedAttention()}});

  // Debian's LibTorch defaults to one intra-op thread.
  const int threads = config.threads > 0
                          ? config.threads
                          : static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  fd::session::SetIntraOpThreads(threads);

  // Signals: forwarded to the main loop below (ForwardSignal). Blocked
  // before any of our threads starts (they inherit the mask), so none of
  // them is interrupted; the main thread unblocks them once serving.
  if (pipe2(g_signal_pipe, O_CLOEXEC) != 0) {
    return Fail(absl::InternalError("cannot create the signal pipe"));
  }
  struct sigaction forward = {};
  forward.sa_handler = ForwardSignal;
  sigemptyset(&forward.sa_mask);
  // No SA_RESTART: the main thread's read() of the pipe returns EINTR and
  // reads again. Under ThreadSanitizer, which defers a handler to the
  // thread's next intercepted call, a restarted read() never returned, so
  // SIGHUP and SIGTERM went unhandled (server.python_interop, tsan preset).
  // The kernel offers a process's signal to its main thread first, and our
  // other threads block these signals, so no other call sees EINTR.
  forward.sa_flags = 0;
  sigset_t signals;
  sigemptyset(&signals);
  for (int signo : {SIGTERM, SIGINT, SIGHUP}) {
    sigaction(signo, &forward, nullptr);
    sigaddset(&signals, signo);
  }
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);

  fd::server::ServerOptions options;
  options.config = config;
  absl::StatusOr<std::unique_ptr<fd::server::FrameDiffuserServer>> server =
      fd::server::FrameDiffuserServer::Start(std::move(options));
  if (!server.ok()) return Fail(server.status());

  if (!config.port_file.empty()) {
    // Written whole under a temporary name, then renamed, so a reader never
    // sees a partial number.
    const std::string tmp = config.port_file + ".tmp";
    {
      std::ofstream out(tmp, std::ios::trunc);
      out << (*server)->port() << "\n";
    }
    if (std::rename(tmp.c_str(), config.port_file.c_str()) != 0) {
      return Fail(absl::InvalidArgumentError(
          absl::StrCat("--port_file: cannot write '", config.port_file, "'")));
    }
  }
  std::cerr << "framediffuser-server listening on port " << (*server)->port()
            << ((*server)->metrics_port() != 0
                    ? absl::StrCat(", metrics on port ", (*server)->metrics_port())
                    : std::string())
            << std::endl;

  pthread_sigmask(SIG_UNBLOCK, &signals, nullptr);
  while (true) {
    const int signal = NextSignal();
    if (signal == SIGHUP) {
      absl::Status rescanned = (*server)->Rescan();
      if (!rescanned.ok()) {
        fd::server::LogWarning("repository_rescan_failed",
                               {{"message", std::string(rescanned.message())}});
      }
      continue;
    }
    LogEvent("server_draining", {{"signal", signal == SIGTERM ? "SIGTERM" : "SIGINT"}});
    (*server)->Shutdown();
    return 0;
  }
}
