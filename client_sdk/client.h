// FrameDiffuser C++ SDK: the entry point a game client links.
//
//   fd::client::ClientOptions options;
//   options.target = "render.example.com:50051";
//   options.use_tls = true;                 // optional
//   options.bearer_token = "...";           // optional, sent as authorization
//   auto client = fd::client::Client::Create(options);        // StatusOr
//   auto envs = (*client)->ListEnvironments();                 // StatusOr
//   fd::client::SessionOptions session_options;
//   session_options.environment = "downtown_west";
//   auto session = (*client)->OpenSession(session_options);    // StatusOr
//
// See session.h for rendering. A Client is cheap to keep and thread-safe; it
// owns one gRPC channel shared by its sessions (which keep it alive, so a
// Session may outlive its Client). Errors are absl::Status with the gRPC
// code and message of the server; an unreachable server is UNAVAILABLE with
// a message naming the target.
#ifndef FD_CLIENT_SDK_CLIENT_H_
#define FD_CLIENT_SDK_CLIENT_H_

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/time/time.h"
#include "client_sdk/session.h"

namespace fd::client {

struct ClientOptions {
  // gRPC target: "host:port", "ipv4:127.0.0.1:50051", "dns:///name:port", ...
  std::string target = "localhost:50051";
  // TLS: server certificate checked against tls_root_certs_pem (PEM; empty =
  // the system roots). Optional client certificate for mutual TLS.
  bool use_tls = false;
  std::string tls_root_certs_pem;
  std::string tls_client_cert_pem;
  std::string tls_client_key_pem;
  // Overrides the host name checked in the server certificate (tests).
  std::string tls_server_name_override;
  // Sent as "authorization: Bearer <token>" on every call when non-empty.
  std::string bearer_token;
  // Deadline of unary calls (ListEnvironments, CheckHealth).
  absl::Duration rpc_timeout = absl::Seconds(10);
  // Upper bound of gRPC's reconnect backoff: how quickly a restarted server
  // is noticed by failover.
  absl::Duration max_reconnect_backoff = absl::Seconds(1);
  // HTTP/2 keepalive pings while calls are active, so a server that vanished
  // without closing the connection (node loss) is noticed and failover
  // starts; zero = off. The server must permit pings this frequent.
  absl::Duration keepalive_time = absl::ZeroDuration();
  absl::Duration keepalive_timeout = absl::Seconds(10);
};

enum class Readiness { kUnknown, kLoading, kReady, kFailed, kUnloading };

// One environment (a trained model) the server serves.
struct Environment {
  std::string name;
  std::string description;
  std::string prompt;
  uint32_t native_width = 0;
  uint32_t native_height = 0;
  uint32_t default_steps = 0;
  uint32_t max_steps = 0;
  Scheduler default_scheduler = Scheduler::kDefault;
  SkyMode default_sky_mode = SkyMode::kDefault;
  Readiness readiness = Readiness::kUnknown;
  std::string readiness_detail;
  uint32_t min_size = 0;
  uint32_t max_size = 0;
};

// grpc.health.v1 serving status.
enum class HealthStatus { kUnknown, kServing, kNotServing, kServiceUnknown };

class Connection;

class Client {
 public:
  // Creates the channel; does not wait for a connection (calls do).
  // INVALID_ARGUMENT for an empty target or unusable TLS material.
  static absl::StatusOr<std::unique_ptr<Client>> Create(const ClientOptions& options);
  ~Client();

  const ClientOptions& options() const;

  absl::StatusOr<std::vector<Environment>> ListEnvironments();

  // grpc.health.v1.Health/Check for `service` ("" = the whole server; the
  // server also registers per-environment names). NOT_FOUND when the server
  // does not know `service`.
  absl::StatusOr<HealthStatus> CheckHealth(const std::string& service = "");

  // Opens a session (blocking until the server answers with SessionOpened or
  // options.open_timeout passes). Errors as the server reports them:
  // NOT_FOUND unknown environment, INVALID_ARGUMENT bad sizes/steps,
  // UNAVAILABLE environment loading or server unreachable, ...
  absl::StatusOr<std::unique_ptr<Session>> OpenSession(const SessionOptions& options);

 private:
  explicit Client(std::shared_ptr<Connection> connection);
  std::shared_ptr<Connection> connection_;
};

// Names for logs and CLIs: "ready", "uni_pc", "client_image", "serving", ...
const char* ReadinessName(Readiness readiness);
const char* SchedulerName(Scheduler scheduler);
const char* SkyModeName(SkyMode sky_mode);
const char* HealthStatusName(HealthStatus status);

}  // namespace fd::client

#endif  // FD_CLIENT_SDK_CLIENT_H_
