#include "server/server.h"

#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>

#include <algorithm>
#include <fstream>
#include <sstream>
#include <thread>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "server/embedded_environment.h"
#include "server/log.h"
#include "session/compute_runtime.h"

#ifndef FD_VERSION
#define FD_VERSION "0.0.0"
#endif
#ifndef FD_GIT_COMMIT
#define FD_GIT_COMMIT "unknown"
#endif

namespace fd::server {
namespace {

absl::StatusOr<std::string> ReadFile(const std::string& path, const char* flag) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::InvalidArgumentError(absl::StrCat(flag, ": cannot read '", path, "'"));
  std::ostringstream text;
  text << in.rdbuf();
  return text.str();
}

absl::StatusOr<std::shared_ptr<grpc::ServerCredentials>> MakeCredentials(
    const ServerConfig& config) {
  if (config.tls_cert.empty() && config.tls_key.empty()) {
    return grpc::InsecureServerCredentials();
  }
  grpc::SslServerCredentialsOptions ssl(
      config.tls_client_ca.empty() ? GRPC_SSL_DONT_REQUEST_CLIENT_CERTIFICATE
                                   : GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY);
  absl::StatusOr<std::string> cert = ReadFile(config.tls_cert, "--tls_cert");
  if (!cert.ok()) return cert.status();
  absl::StatusOr<std::string> key = ReadFile(config.tls_key, "--tls_key");
  if (!key.ok()) return key.status();
  ssl.pem_key_cert_pairs.push_back({*key, *cert});
  if (!config.tls_client_ca.empty()) {
    absl::StatusOr<std::string> ca = ReadFile(config.tls_client_ca, "--tls_client_ca");
    if (!ca.ok()) return ca.status();
    ssl.pem_root_certs = *ca;
  }
  return grpc::SslServerCredentials(ssl);
}

}  // namespace

std::string EnvironmentHealthName(const std::string& environment) {
  return absl::StrCat(kServiceName, "/", environment);
}

FrameDiffuserServer::FrameDiffuserServer(ServerOptions options) : options_(std::move(options)) {}

FrameDiffuserServer::~FrameDiffuserServer() { Shutdown(absl::ZeroDuration()); }

absl::StatusOr<std::unique_ptr<FrameDiffuserServer>> FrameDiffuserServer::Start(
    ServerOptions options) {
  std::unique_ptr<FrameDiffuserServer> server(new FrameDiffuserServer(std::move(options)));
  if (absl::Status status = server->Init(); !status.ok()) {
    server->Shutdown(absl::ZeroDuration());
    return status;
  }
  return server;
}

absl::Status FrameDiffuserServer::Init() {
  const ServerConfig& config = options_.config;
  if (absl::Status valid = ValidateServerConfig(config); !valid.ok()) return valid;
  absl::StatusOr<session::EnvironmentLoadOptions> load =
      session::ParseLoadOptions(config.device, config.dtype);
  if (!load.ok()) return load.status();
  device_ = session::DeviceName(*load);

  // Metrics first: everything else reports to them.
  metrics_ = std::make_unique<ServerMetrics>(
      BuildInfo{FD_VERSION, FD_GIT_COMMIT, session::TorchVersion(), device_});
  metrics_->SampleDeviceMemoryAtScrape(device_);
  if (!config.metrics_listen.empty()) {
    absl::StatusOr<int> port = metrics_->StartExposer(config.metrics_listen);
    if (!port.ok()) {
      return absl::Status(port.status().code(),
                          absl::StrCat("--metrics_listen: ", port.status().message()));
    }
    metrics_port_ = *port;
  }

  if (!config.auth_tokens_file.empty()) {
    absl::StatusOr<TokenAuthenticator> auth =
        TokenAuthenticator::LoadTokenFile(config.auth_tokens_file);
    if (!auth.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat("--auth_tokens_file: ", auth.status().message()));
    }
    auth_ = std::make_unique<TokenAuthenticator>(*std::move(auth));
  }

  session::SessionStoreOptions store_options;
  store_options.max_sessions = static_cast<size_t>(config.max_sessions);
  store_options.max_sessions_per_environment =
      static_cast<size_t>(config.max_sessions_per_environment);
  store_options.max_sessions_per_client = static_cast<size_t>(config.max_sessions_per_client);
  store_options.idle_timeout = config.idle_timeout;
  absl::StatusOr<std::unique_ptr<session::SessionStore>> store = session::SessionStore::Create(
      store_options, options_.clock != nullptr ? options_.clock : session::RealClock::Get(),
      metrics_.get());
  if (!store.ok()) return store.status();
  store_ = *std::move(store);

  session::EnvironmentRegistryOptions registry_options;
  registry_options.load = *load;
  registry_options.batcher.mode = ToBatchingMode(config);
  registry_options.batcher.max_batch_size = config.max_batch_size;
  registry_options.batcher.max_queue_delay = config.max_queue_delay;
  registry_options.batcher.max_queue_size = config.max_queue_size;
  registry_options.pipeline.batch_invariant = config.batch_invariant;
  // Workers x threads per worker (session/compute_runtime.h: the threading
  // policy, docs/BENCHMARKS.md "Threading policy").
  session::WorkerThreadsRequest parallelism;
  parallelism.cores = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  parallelism.cpu = session::IsCpuDevice(*load);
  parallelism.max_batch_size = config.max_batch_size;
  parallelism.workers = config.scheduler_workers;
  parallelism.threads = config.threads;
  const session::WorkerThreads resolved = session::ResolveWorkerThreads(parallelism);
  registry_options.batcher.workers = resolved.workers;
  scheduler_workers_ = resolved.workers;
  // Set on each worker thread: OpenMP keeps the thread count per thread, so
  // the thread count set in main does not reach the workers.
  registry_options.batcher.threads_per_worker = resolved.threads_per_worker;
  threads_per_worker_ = resolved.threads_per_worker;
  if (resolved.oversubscribed) {
    LogEvent(
        "threads_oversubscribed",
        {{"message", absl::StrCat("--scheduler_workers ", resolved.workers, " x --threads ",
                                  resolved.threads_per_worker, " exceeds the ", parallelism.cores,
                                  " cores: OpenMP threads will sleep between kernels and "
                                  "frames will be slower than with fewer threads")}});
  }
  // More threads never slower: each environment's steps are timed at 1 and
  // at threads_per_worker threads, and at 1 with the ControlNet beside the
  // UNet on a free core, when it loads, and the fastest kept.
  registry_options.choose_intra_op_threads = true;
  registry_options.allow_controlnet_beside_unet = config.controlnet_beside_unet;
  registry_options.on_threads_chosen =
      [](const std::string& name, const session::EnvironmentRegistryOptions::ThreadsChosen& c) {
        LogEvent("intra_op_threads", {{"environment", name},
                                      {"threads", static_cast<int64_t>(c.threads)},
                                      {"controlnet_beside_unet", c.controlnet_beside_unet},
                                      {"step_ms_1_thread", c.step_ms_one},
                                      {"step_ms_max_threads", c.step_ms_many},
                                      {"step_ms_beside", c.step_ms_beside},
                                      {"vae_on_free_core", c.vae_on_free_core},
                                      {"frame_ms_vae_1_thread", c.frame_ms_vae_one},
                                      {"frame_ms_vae_2_threads", c.frame_ms_vae_two}});
      };
  registry_options.batcher_observer = metrics_.get();
  registry_options.pipeline_factory = options_.pipeline_factory;
  registry_options.loader = options_.loader;
  registry_options.on_readiness_changed = [this](const std::string& name,
                                                 std::optional<session::Readiness> readiness) {
    OnReadiness(name, readiness);
  };
  registry_options.on_load_finished = [this](const std::string& name, const std::string& dir,
                                             const absl::Status& status, double seconds) {
    metrics_->OnModelLoad(name, status.ok(), seconds);
    if (status.ok()) {
      LogEvent("environment_load", {{"environment", name}, {"dir", dir}, {"seconds", seconds}});
    } else {
      LogError("environment_load_failed", {{"environment", name},
                                           {"dir", dir},
                                           {"seconds", seconds},
                                           {"code", absl::StatusCodeToString(status.code())},
                                           {"message", std::string(status.message())}});
    }
    if (options_.on_load_finished) options_.on_load_finished(name, status);
  };
  registry_options.on_removing = [this](const std::string& name) {
    std::vector<std::shared_ptr<session::Session>> evicted =
        store_->EvictEnvironment(name, absl::StrCat("environment '", name, "' was removed"));
    if (service_ != nullptr) service_->EndStreamsOf(evicted, session::EndReason::kEvicted);
    LogEvent("environment_remove",
             {{"environment", name}, {"sessions_evicted", static_cast<int64_t>(evicted.size())}});
  };
  registry_ = std::make_unique<session::EnvironmentRegistry>(std::move(registry_options));

  RenderServiceDeps deps;
  deps.registry = registry_.get();
  deps.store = store_.get();
  deps.metrics = metrics_.get();
  deps.auth = auth_.get();
  deps.limits.min_size = static_cast<uint32_t>(config.min_size);
  deps.limits.max_size = static_cast<uint32_t>(config.max_size);
  deps.limits.max_steps = static_cast<uint32_t>(config.max_steps);
  deps.limits.max_frames_in_flight = static_cast<uint32_t>(config.max_frames_in_flight);
  deps.max_message_bytes = static_cast<uint64_t>(config.max_message_bytes);
  service_ = std::make_unique<RenderService>(deps);

  // Environments: given ones, the repository's, or the embedded default.
  for (const auto& [name, model] : options_.environments) {
    if (absl::Status added = registry_->AddLoaded(name, model); !added.ok()) return added;
  }
  if (!config.model_repository.empty()) {
    if (absl::Status scanned = registry_->Rescan(config.model_repository); !scanned.ok()) {
      return absl::NotFoundError(absl::StrCat("--model_repository: ", scanned.message()));
    }
  } else if (options_.environments.empty()) {
    const absl::Time start = absl::Now();
    absl::StatusOr<std::shared_ptr<session::EnvironmentModel>> embedded =
        CreateEmbeddedEnvironment(*load);
    const double seconds = absl::ToDoubleSeconds(absl::Now() - start);
    metrics_->OnModelLoad(kEmbeddedEnvironmentName, embedded.ok(), seconds);
    if (!embedded.ok()) return embedded.status();
    if (absl::Status added = registry_->AddLoaded(kEmbeddedEnvironmentName, *embedded);
        !added.ok()) {
      return added;
    }
    LogEvent("environment_load", {{"environment", kEmbeddedEnvironmentName},
                                  {"dir", "(embedded: environments/street)"},
                                  {"seconds", seconds}});
  }

  absl::StatusOr<std::shared_ptr<grpc::ServerCredentials>> credentials = MakeCredentials(config);
  if (!credentials.ok()) return credentials.status();
  grpc::EnableDefaultHealthCheckService(true);
  if (config.reflection) grpc::reflection::InitProtoReflectionServerBuilderPlugin();
  grpc::ServerBuilder builder;
  builder.AddListeningPort(config.listen, *credentials, &port_);
  // The streams refuse messages above --max_message_bytes themselves
  // (stream_controller.h: the session stays resumable, no race with a
  // half-close). gRPC's own limit sits above it, at 2x + 1 MiB, only to
  // bound what one read can make us hold.
  builder.SetMaxReceiveMessageSize(static_cast<int>(std::min<int64_t>(
      2 * config.max_message_bytes + (int64_t{1} << 20), std::numeric_limits<int>::max())));
  builder.SetMaxSendMessageSize(std::numeric_limits<int>::max());
  builder.RegisterService(service_.get());
  std::unique_ptr<grpc::Server> grpc_server = builder.BuildAndStart();
  if (grpc_server == nullptr || port_ == 0) {
    return absl::UnavailableError(absl::StrCat("--listen: cannot listen on '", config.listen, "'"));
  }
  {
    absl::MutexLock lock(&mu_);
    grpc_server_ = std::move(grpc_server);
    serving_ = true;
  }
  UpdateServiceHealth();

  reaper_ = std::make_unique<session::SessionReaper>(
      store_.get(), config.reaper_interval,
      [this](const std::vector<std::shared_ptr<session::Session>>& expired) {
        service_->EndStreamsOf(expired, session::EndReason::kExpired);
      });

  if (options_.wait_for_environments) registry_->AwaitLoads();
  LogEvent("server_start", {{"listen", config.listen},
                            {"port", port_},
                            {"metrics_port", metrics_port_},
                            {"device", device_},
                            {"dtype", config.dtype},
                            {"batching", config.batching},
                            {"batch_invariant", config.batch_invariant},
                            {"controlnet_beside_unet", config.controlnet_beside_unet},
                            {"scheduler_workers", static_cast<int64_t>(scheduler_workers_)},
                            {"threads_per_worker", static_cast<int64_t>(threads_per_worker_)},
                            {"environments", static_cast<int64_t>(registry_->List().size())},
                            {"tls", !config.tls_cert.empty()},
                            {"auth", auth_ != nullptr}});
  return absl::OkStatus();
}

std::string FrameDiffuserServer::address() const { return absl::StrCat("127.0.0.1:", port_); }

void FrameDiffuserServer::OnReadiness(const std::string& name,
                                      std::optional<session::Readiness> readiness) {
  if (readiness.has_value()) {
    metrics_->SetEnvironmentState(name, session::ReadinessName(*readiness));
  } else {
    metrics_->RemoveEnvironment(name);
  }
  UpdateServiceHealth();
}

void FrameDiffuserServer::UpdateServiceHealth() {
  absl::MutexLock lock(&mu_);
  if (!serving_ || shut_down_ || grpc_server_ == nullptr) return;
  grpc::HealthCheckServiceInterface* health = grpc_server_->GetHealthCheckService();
  if (health == nullptr) return;
  bool any_ready = false;
  for (const session::EnvironmentInfo& info : registry_->List()) {
    const bool ready = info.readiness == session::Readiness::kReady;
    any_ready = any_ready || ready;
    health->SetServingStatus(EnvironmentHealthName(info.name), ready);
  }
  health->SetServingStatus(kServiceName, any_ready);
  health->SetServingStatus("", true);
}

absl::Status FrameDiffuserServer::Rescan() {
  if (options_.config.model_repository.empty()) {
    return absl::FailedPreconditionError("no --model_repository to rescan");
  }
  LogEvent("repository_rescan", {{"dir", options_.config.model_repository}});
  return registry_->Rescan(options_.config.model_repository);
}

void FrameDiffuserServer::ExpireIdleSessionsNow() {
  std::vector<std::shared_ptr<session::Session>> expired = store_->ExpireIdle();
  service_->EndStreamsOf(expired, session::EndReason::kExpired);
}

void FrameDiffuserServer::Shutdown(absl::Duration timeout) {
  if (timeout < absl::ZeroDuration()) timeout = options_.config.drain_timeout;
  {
    absl::MutexLock lock(&mu_);
    if (shut_down_) return;
    shut_down_ = true;
  }
  const absl::Time start = absl::Now();
  const absl::Time deadline = start + timeout;
  int drained_sessions = 0;
  bool streams_done = true;
  if (grpc_server_ != nullptr) {
    // Load balancers stop sending new sessions here first.
    if (grpc::HealthCheckServiceInterface* health = grpc_server_->GetHealthCheckService()) {
      health->Shutdown();
    }
  }
  if (store_ != nullptr) drained_sessions = static_cast<int>(store_->DrainAll().size());
  if (service_ != nullptr) {
    service_->BeginDrain();
    streams_done = service_->AwaitNoStreams(deadline);
  }
  if (grpc_server_ != nullptr) {
    // Streams still open at the deadline are cancelled.
    grpc_server_->Shutdown(std::chrono::system_clock::now());
    grpc_server_->Wait();
  }
  if (reaper_ != nullptr) reaper_->Stop();
  if (registry_ != nullptr) registry_->Shutdown();
  if (service_ != nullptr || registry_ != nullptr) {
    LogEvent("server_stop", {{"sessions_drained", drained_sessions},
                             {"streams_drained_in_time", streams_done},
                             {"seconds", absl::ToDoubleSeconds(absl::Now() - start)}});
  }
}

}  // namespace fd::server
