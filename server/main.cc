// framediffuser-server: serves FrameDiffuser environments over gRPC.
//
//   framediffuser-server --listen 0.0.0.0:50051 --model_repository /models
//       --metrics_listen 0.0.0.0:9464
//
// Signals: SIGTERM / SIGINT drain gracefully (exit 0 within --drain_timeout
// plus the frames in flight); SIGHUP rescans the model repository. Every
// option: --help.
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

int Fail(const absl::Status& status) {
  std::cerr << "framediffuser-server: " << status.message() << "\n"
            << "(--help lists every option)\n";
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  using fd::server::LogEvent;
  fd::session::UsePassiveOpenMpWaitPolicy(argv);  // may re-execute the server
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
  const char* wait_policy = std::getenv("OMP_WAIT_POLICY");
  LogEvent("process_tuning", {{"malloc", malloc_tuning},
                              {"blas", blas_threads},
                              {"omp_wait_policy", wait_policy != nullptr ? wait_policy : ""}});

  // Debian's LibTorch defaults to one intra-op thread.
  const int threads = config.threads > 0
                          ? config.threads
                          : static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  fd::session::SetIntraOpThreads(threads);

  // Signals are taken by sigwait below: block them before any thread starts
  // (threads inherit the mask), so no other thread is interrupted.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGHUP);
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

  while (true) {
    int signal = 0;
    if (sigwait(&signals, &signal) != 0) continue;
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
