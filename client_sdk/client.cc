#include "client_sdk/client.h"

#include <grpcpp/grpcpp.h>

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "client_sdk/internal/connection.h"
#include "client_sdk/internal/session_impl.h"
#include "client_sdk/internal/wire.h"
#include "grpc/health/v1/health.grpc.pb.h"

namespace fd::client {
namespace {

void SetDeadline(grpc::ClientContext* context, absl::Duration timeout) {
  context->set_deadline(absl::ToChronoTime(absl::Now() + timeout));
}

// UNAVAILABLE from a unary call: say which server could not be reached.
absl::Status Annotate(const grpc::Status& status, const std::string& target) {
  absl::Status converted = internal::FromGrpc(status);
  if (converted.code() == absl::StatusCode::kUnavailable ||
      converted.code() == absl::StatusCode::kDeadlineExceeded) {
    return absl::Status(converted.code(), absl::StrCat("cannot reach the FrameDiffuser server at ",
                                                       target, ": ", converted.message()));
  }
  return converted;
}

}  // namespace

absl::StatusOr<std::unique_ptr<Client>> Client::Create(const ClientOptions& options) {
  if (options.target.empty()) return absl::InvalidArgumentError("ClientOptions.target is empty");
  std::shared_ptr<grpc::ChannelCredentials> credentials;
  grpc::ChannelArguments args;
  if (options.use_tls) {
    if (options.tls_client_cert_pem.empty() != options.tls_client_key_pem.empty()) {
      return absl::InvalidArgumentError(
          "ClientOptions: tls_client_cert_pem and tls_client_key_pem go together");
    }
    grpc::SslCredentialsOptions ssl;
    ssl.pem_root_certs = options.tls_root_certs_pem;
    ssl.pem_cert_chain = options.tls_client_cert_pem;
    ssl.pem_private_key = options.tls_client_key_pem;
    credentials = grpc::SslCredentials(ssl);
    if (!options.tls_server_name_override.empty()) {
      args.SetSslTargetNameOverride(options.tls_server_name_override);
    }
  } else {
    credentials = grpc::InsecureChannelCredentials();
  }
  // Frames are megabytes: no receive limit on our side (the server has its own).
  args.SetMaxReceiveMessageSize(-1);
  args.SetMaxSendMessageSize(-1);
  const int max_backoff_ms = static_cast<int>(
      std::max<int64_t>(absl::ToInt64Milliseconds(options.max_reconnect_backoff), 1));
  args.SetInt(GRPC_ARG_MAX_RECONNECT_BACKOFF_MS, max_backoff_ms);
  args.SetInt(GRPC_ARG_INITIAL_RECONNECT_BACKOFF_MS, std::min(max_backoff_ms, 1000));
  args.SetInt(GRPC_ARG_MIN_RECONNECT_BACKOFF_MS, std::min(max_backoff_ms, 1000));
  if (options.keepalive_time > absl::ZeroDuration()) {
    args.SetInt(GRPC_ARG_KEEPALIVE_TIME_MS,
                static_cast<int>(absl::ToInt64Milliseconds(options.keepalive_time)));
    args.SetInt(GRPC_ARG_KEEPALIVE_TIMEOUT_MS,
                static_cast<int>(absl::ToInt64Milliseconds(options.keepalive_timeout)));
  }
  std::shared_ptr<grpc::Channel> channel =
      grpc::CreateCustomChannel(options.target, credentials, args);
  if (channel == nullptr) {
    return absl::InvalidArgumentError(absl::StrCat("cannot create a channel to ", options.target));
  }
  return std::unique_ptr<Client>(
      new Client(std::make_shared<Connection>(options, std::move(channel))));
}

Client::Client(std::shared_ptr<Connection> connection) : connection_(std::move(connection)) {}
Client::~Client() = default;

const ClientOptions& Client::options() const { return connection_->options(); }

absl::StatusOr<std::vector<Environment>> Client::ListEnvironments() {
  grpc::ClientContext context;
  connection_->Prepare(&context);
  SetDeadline(&context, connection_->options().rpc_timeout);
  framediffuser::v1::ListEnvironmentsResponse response;
  grpc::Status status = connection_->stub()->ListEnvironments(
      &context, framediffuser::v1::ListEnvironmentsRequest(), &response);
  if (!status.ok()) return Annotate(status, connection_->options().target);
  std::vector<Environment> environments;
  for (const auto& environment : response.environments()) {
    environments.push_back(internal::FromWire(environment));
  }
  return environments;
}

absl::StatusOr<HealthStatus> Client::CheckHealth(const std::string& service) {
  grpc::ClientContext context;
  connection_->Prepare(&context);
  SetDeadline(&context, connection_->options().rpc_timeout);
  grpc::health::v1::HealthCheckRequest request;
  request.set_service(service);
  grpc::health::v1::HealthCheckResponse response;
  auto stub = grpc::health::v1::Health::NewStub(connection_->shared_channel());
  grpc::Status status = stub->Check(&context, request, &response);
  if (!status.ok()) return Annotate(status, connection_->options().target);
  switch (response.status()) {
    case grpc::health::v1::HealthCheckResponse::SERVING:
      return HealthStatus::kServing;
    case grpc::health::v1::HealthCheckResponse::NOT_SERVING:
      return HealthStatus::kNotServing;
    case grpc::health::v1::HealthCheckResponse::SERVICE_UNKNOWN:
      return HealthStatus::kServiceUnknown;
    default:
      return HealthStatus::kUnknown;
  }
}

absl::StatusOr<std::unique_ptr<Session>> Client::OpenSession(const SessionOptions& options) {
  absl::StatusOr<std::unique_ptr<SessionImpl>> impl = SessionImpl::Open(connection_, options);
  if (!impl.ok()) return impl.status();
  return std::unique_ptr<Session>(new Session(std::move(*impl)));
}

const char* ReadinessName(Readiness readiness) {
  switch (readiness) {
    case Readiness::kLoading:
      return "loading";
    case Readiness::kReady:
      return "ready";
    case Readiness::kFailed:
      return "failed";
    case Readiness::kUnloading:
      return "unloading";
    default:
      return "unknown";
  }
}

const char* SchedulerName(Scheduler scheduler) {
  switch (scheduler) {
    case Scheduler::kUniPC:
      return "unipc";
    case Scheduler::kDpmSolverPP2M:
      return "dpmpp_2m";
    case Scheduler::kDdim:
      return "ddim";
    case Scheduler::kEuler:
      return "euler";
    default:
      return "default";
  }
}

const char* SkyModeName(SkyMode sky_mode) {
  switch (sky_mode) {
    case SkyMode::kClientImage:
      return "client_image";
    case SkyMode::kPreviousOutput:
      return "previous_output";
    case SkyMode::kOff:
      return "off";
    default:
      return "default";
  }
}

const char* HealthStatusName(HealthStatus status) {
  switch (status) {
    case HealthStatus::kServing:
      return "serving";
    case HealthStatus::kNotServing:
      return "not_serving";
    case HealthStatus::kServiceUnknown:
      return "service_unknown";
    default:
      return "unknown";
  }
}

}  // namespace fd::client
