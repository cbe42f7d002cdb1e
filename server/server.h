// FrameDiffuserServer: everything framediffuser-server runs, assembled from
// a ServerConfig — the environments (model repository, or the embedded
// default), the session store and its reaper, the render service, standard
// gRPC health (per environment too) and reflection, TLS, bearer-token auth,
// and the prometheus endpoint. main.cc adds only flags and signals; tests
// start it in-process on port 0.
//
// Health service names: "" (the whole server: SERVING until it drains),
// "framediffuser.v1.FrameDiffuser" (SERVING while at least one environment
// is READY) and "framediffuser.v1.FrameDiffuser/<environment>" (SERVING
// while that environment is READY).
//
// Shutdown (SIGTERM/SIGINT in main): health NOT_SERVING, the session store
// refuses new sessions, every stream gets a DRAINING notice and its frames
// already read are rendered and answered, then the streams end with
// UNAVAILABLE; whatever is still open at drain_timeout is cancelled.
//
// Ownership: owns every part. Thread-safety: all methods are thread-safe;
// Shutdown may be called from any thread (not from a gRPC callback).
#ifndef FD_SERVER_SERVER_H_
#define FD_SERVER_SERVER_H_

#include <functional>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "server/auth.h"
#include "server/metrics.h"
#include "server/render_service.h"
#include "server/server_config.h"
#include "session/clock.h"
#include "session/environment_registry.h"
#include "session/session_reaper.h"
#include "session/session_store.h"

namespace grpc {
class Server;
}

namespace fd::server {

inline constexpr char kServiceName[] = "framediffuser.v1.FrameDiffuser";

// The health service name of one environment.
std::string EnvironmentHealthName(const std::string& environment);

struct ServerOptions {
  ServerConfig config;
  // Environments served in addition to the repository's (tests): name and
  // loaded model. When the repository is empty and this is empty, the
  // embedded default environment is served.
  std::vector<std::pair<std::string, std::shared_ptr<const session::EnvironmentModel>>>
      environments;
  // Tests wrap the real pipeline (nullptr: session::ModelFramePipeline).
  session::PipelineFactory pipeline_factory;
  // Loads repository folders (nullptr: the model's loader); tests block it.
  session::EnvironmentLoader loader;
  // Session store clock (nullptr: the real clock). Must outlive the server.
  const session::Clock* clock = nullptr;
  // Wait for the repository's environments to finish loading before Start
  // returns (tests; main serves at once and reports LOADING meanwhile).
  bool wait_for_environments = false;
  // Called on the registry's loader thread each time a repository folder
  // finished loading or reloading, after the server logged and counted it
  // (tests wait on it). On success the new model already serves (unless the
  // folder was removed meanwhile): frames handed to the environment from
  // then on render on it, while the previous model's batcher may still be
  // rendering the frames it had (the registry's AwaitLoads also waits for
  // those). Must not block.
  std::function<void(const std::string& name, const absl::Status& status)> on_load_finished;
};

class FrameDiffuserServer {
 public:
  // Validates the config, loads what must be loaded and starts serving.
  // INVALID_ARGUMENT (config, device, dtype, TLS files, token file),
  // NOT_FOUND (repository), UNAVAILABLE (cannot bind the listen or metrics
  // address), errors from the embedded environment.
  static absl::StatusOr<std::unique_ptr<FrameDiffuserServer>> Start(ServerOptions options);
  // Shutdown(absl::ZeroDuration()) if still running.
  ~FrameDiffuserServer();

  FrameDiffuserServer(const FrameDiffuserServer&) = delete;
  FrameDiffuserServer& operator=(const FrameDiffuserServer&) = delete;

  int port() const { return port_; }
  // 0 without a metrics endpoint.
  int metrics_port() const { return metrics_port_; }
  std::string address() const;  // "127.0.0.1:<port>" style, for tests and logs

  // Rescans the model repository (SIGHUP). FAILED_PRECONDITION without one.
  absl::Status Rescan();

  // Graceful shutdown, bounded by `timeout` (config.drain_timeout when
  // negative). Idempotent; returns once the gRPC server stopped and every
  // scheduler finished.
  void Shutdown(absl::Duration timeout = absl::InfiniteDuration() * -1);

  session::EnvironmentRegistry& registry() { return *registry_; }
  session::SessionStore& store() { return *store_; }
  ServerMetrics& metrics() { return *metrics_; }
  RenderService& service() { return *service_; }
  // Runs one idle-expiry pass now (tests drive it with a fake clock).
  void ExpireIdleSessionsNow();

 private:
  explicit FrameDiffuserServer(ServerOptions options);
  absl::Status Init();
  void OnReadiness(const std::string& name, std::optional<session::Readiness> readiness);
  void UpdateServiceHealth();

  ServerOptions options_;
  std::string device_;          // resolved --device, e.g. "cpu", "cuda:0"
  int scheduler_workers_ = 1;   // resolved --scheduler_workers (for the start-up log)
  int threads_per_worker_ = 1;  // resolved --threads
  std::unique_ptr<ServerMetrics> metrics_;
  std::unique_ptr<TokenAuthenticator> auth_;
  std::unique_ptr<session::SessionStore> store_;
  std::unique_ptr<session::EnvironmentRegistry> registry_;
  std::unique_ptr<RenderService> service_;
  std::unique_ptr<grpc::Server> grpc_server_;
  std::unique_ptr<session::SessionReaper> reaper_;
  int port_ = 0;
  int metrics_port_ = 0;

  absl::Mutex mu_;
  bool shut_down_ ABSL_GUARDED_BY(mu_) = false;
  bool serving_ ABSL_GUARDED_BY(mu_) = false;  // grpc_server_ built (health calls allowed)
};

}  // namespace fd::server

#endif  // FD_SERVER_SERVER_H_
