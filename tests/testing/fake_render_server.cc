#include "tests/testing/fake_render_server.h"

#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>
#include <zstd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <deque>
#include <map>
#include <mutex>
#include <optional>
#include <random>
#include <set>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "framediffuser/v1/render_service.grpc.pb.h"

namespace fd::testing {
namespace {

namespace v1 = ::framediffuser::v1;
using client::DType;
using client::ImageF;
using client::ImageView;

struct FakeSession {
  std::string id;
  std::string token;
  v1::SessionSettings settings;
  ImageF previous;  // empty: zeros
  std::optional<uint64_t> last_frame_index;
  bool closed = false;
};

size_t ElementSize(v1::DType dtype) {
  switch (dtype) {
    case v1::DTYPE_UINT8:
      return 1;
    case v1::DTYPE_FLOAT16:
      return 2;
    case v1::DTYPE_FLOAT32:
      return 4;
    default:
      return 0;
  }
}

DType ToDType(v1::DType dtype) {
  return dtype == v1::DTYPE_FLOAT16   ? DType::kFloat16
         : dtype == v1::DTYPE_FLOAT32 ? DType::kFloat32
                                      : DType::kUint8;
}

std::string RandomHex() {
  static std::mt19937_64 rng(12345);
  static std::mutex mu;
  std::lock_guard<std::mutex> lock(mu);
  static constexpr char kHex[] = "0123456789abcdef";
  std::string id(32, '0');
  for (char& c : id) c = kHex[rng() & 0xf];
  return id;
}

bool IsSessionIdShape(const std::string& s) {
  return s.size() == 32 && std::all_of(s.begin(), s.end(), [](char c) {
           return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'f');
         });
}

// Decodes and validates a wire image like the real server does; the error
// names the field (e.g. "frame.gbuffer.depth.channels: expected 1, got 3").
absl::StatusOr<ImageF> DecodeImage(const v1::Image& image, uint32_t channels, uint32_t width,
                                   uint32_t height, const std::string& field) {
  if (image.channels() != channels) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, ".channels: expected ", channels, ", got ", image.channels()));
  }
  if (image.width() != width || image.height() != height) {
    return absl::InvalidArgumentError(absl::StrCat(field, ": expected ", width, "x", height,
                                                   ", got ", image.width(), "x", image.height()));
  }
  const size_t element = ElementSize(image.dtype());
  if (element == 0) {
    return absl::InvalidArgumentError(absl::StrCat(field, ".dtype: unsupported"));
  }
  const size_t expected = size_t(width) * height * channels * element;
  std::string raw;
  const std::string* bytes = &image.data();
  if (image.compression() == v1::COMPRESSION_ZSTD) {
    raw.resize(expected);
    const size_t got =
        ZSTD_decompress(raw.data(), raw.size(), image.data().data(), image.data().size());
    if (ZSTD_isError(got) || got != expected) {
      return absl::InvalidArgumentError(absl::StrCat(field, ".data: bad zstd frame"));
    }
    bytes = &raw;
  } else if (image.data().size() != expected) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, ".data: ", image.data().size(), " bytes, expected ", expected));
  }
  ImageF out = client::ToFloat(ImageView::Raw(bytes->data(), static_cast<int>(width),
                                              static_cast<int>(height), static_cast<int>(channels),
                                              ToDType(image.dtype())));
  for (float v : out.pixels) {
    if (!std::isfinite(v)) {
      return absl::InvalidArgumentError(absl::StrCat(field, ".data: NaN or Inf"));
    }
  }
  return out;
}

// Quantises to the output dtype, returns the wire image and (via `seen`)
// what the client will see, which becomes the next "previous".
v1::Image EncodeOutput(const ImageF& image, v1::DType dtype, v1::Compression compression,
                       ImageF* seen) {
  v1::Image out;
  out.set_width(image.width);
  out.set_height(image.height);
  out.set_channels(image.channels);
  out.set_dtype(dtype);
  std::string raw;
  const ImageView view = ImageView::Of(image);
  switch (dtype) {
    case v1::DTYPE_FLOAT16: {
      const client::ImageF16 half = client::ToHalf(view);
      raw.assign(reinterpret_cast<const char*>(half.pixels.data()), half.pixels.size() * 2);
      *seen = client::ToFloat(ImageView::Of(half));
      break;
    }
    case v1::DTYPE_FLOAT32:
      raw.assign(reinterpret_cast<const char*>(image.pixels.data()), image.pixels.size() * 4);
      *seen = image;
      break;
    default: {
      const client::Image8 bytes = client::ToUint8(view);
      raw.assign(reinterpret_cast<const char*>(bytes.pixels.data()), bytes.pixels.size());
      *seen = client::ToFloat(ImageView::Of(bytes));
      break;
    }
  }
  if (compression == v1::COMPRESSION_ZSTD) {
    std::string packed(ZSTD_compressBound(raw.size()), '\0');
    packed.resize(ZSTD_compress(packed.data(), packed.size(), raw.data(), raw.size(), 1));
    out.set_data(std::move(packed));
    out.set_compression(v1::COMPRESSION_ZSTD);
  } else {
    out.set_data(std::move(raw));
  }
  return out;
}

class RenderStream;

}  // namespace

// Shared by the FakeRenderServer, its service and the stream reactors.
// Lock order: registry_mu -> a stream's mu -> sessions_mu.
struct FakeRenderServer::State {
  FakeRenderServerOptions options;

  std::mutex registry_mu;
  std::set<RenderStream*> streams;
  bool paused = false;

  std::mutex sessions_mu;
  std::condition_variable frames_cv;
  std::map<std::string, std::shared_ptr<FakeSession>> sessions;
  std::optional<std::pair<uint64_t, BreakPoint>> break_on_frame;
  std::optional<std::pair<int, std::string>> fail_next_open;
  int sessions_opened = 0;
  int sessions_resumed = 0;
  int frames_received = 0;
  int frames_rendered = 0;
  int max_outstanding = 0;
  std::vector<std::string> x_session_ids;
  std::vector<std::string> opened_ids;
  std::vector<std::string> authorization;

  std::mutex server_mu;  // guards the server object and port
  std::unique_ptr<grpc::Service> service;
  std::unique_ptr<grpc::Server> server;
  int port = 0;
};

namespace {

using State = FakeRenderServer::State;
using BreakPoint = FakeRenderServer::BreakPoint;

class RenderStream : public grpc::ServerBidiReactor<v1::RenderRequest, v1::RenderResponse> {
 public:
  RenderStream(std::shared_ptr<State> state, grpc::CallbackServerContext* context)
      : state_(std::move(state)) {
    std::string session_header, authorization;
    for (const auto& [key, value] : context->client_metadata()) {
      if (key == "x-session-id") session_header.assign(value.data(), value.size());
      if (key == "authorization") authorization.assign(value.data(), value.size());
    }
    {
      std::lock_guard<std::mutex> lock(state_->sessions_mu);
      state_->x_session_ids.push_back(session_header);
      state_->authorization.push_back(authorization);
    }
    routing_key_ = session_header;
    {
      std::lock_guard<std::mutex> registry(state_->registry_mu);
      state_->streams.insert(this);
      paused_ = state_->paused;
    }
    std::lock_guard<std::mutex> lock(mu_);
    if (!state_->options.required_token.empty() &&
        authorization != "Bearer " + state_->options.required_token) {
      FinishLocked(
          grpc::Status(grpc::StatusCode::UNAUTHENTICATED, "missing or wrong bearer token"));
      return;
    }
    reading_ = true;
    StartRead(&request_);
  }

  void OnReadDone(bool ok) override {
    std::lock_guard<std::mutex> lock(mu_);
    reading_ = false;
    if (!ok) {
      half_closed_ = true;
      MaybeFinishLocked();
      return;
    }
    if (finishing_) return;
    HandleLocked(request_);
    ContinueReadingLocked();
  }

  void OnWriteDone(bool ok) override {
    std::lock_guard<std::mutex> lock(mu_);
    writing_ = false;
    if (!writes_.empty()) writes_.pop_front();
    if (!ok) {
      writes_.clear();
      FinishLocked(grpc::Status(grpc::StatusCode::CANCELLED, "write failed"));
    }
    StartNextWriteLocked();
    MaybeFinishLocked();
  }

  void OnCancel() override {
    std::lock_guard<std::mutex> lock(mu_);
    // Keep the message being written: gRPC still points at it.
    while (writes_.size() > (writing_ ? 1u : 0u)) writes_.pop_back();
    held_.clear();
    FinishLocked(grpc::Status(grpc::StatusCode::CANCELLED, "cancelled"));
  }

  void OnDone() override {
    // gRPC orders OnDone after OnCancel inside libgrpc++; taking mu_ once
    // makes that visible to ThreadSanitizer (Debian's gRPC is uninstrumented).
    { std::lock_guard<std::mutex> lock(mu_); }
    {
      std::lock_guard<std::mutex> registry(state_->registry_mu);
      state_->streams.erase(this);
    }
    delete this;
  }

  // From test threads (registry_mu held by the caller).
  void Break(grpc::Status status, std::optional<v1::SessionNotice> notice) {
    std::lock_guard<std::mutex> lock(mu_);
    if (finishing_) return;
    // Drop answers not yet on the wire except the one being written.
    while (writes_.size() > (writing_ ? 1u : 0u)) writes_.pop_back();
    held_.clear();
    if (notice.has_value()) {
      v1::RenderResponse response;
      *response.mutable_notice() = *notice;
      QueueWriteLocked(std::move(response));
    }
    FinishLocked(std::move(status));
  }

  void SetPaused(bool paused) {
    std::lock_guard<std::mutex> lock(mu_);
    paused_ = paused;
    if (paused_ || finishing_) return;
    while (!held_.empty() && !finishing_) {
      v1::FrameInput frame = std::move(held_.front());
      held_.pop_front();
      RenderLocked(frame);
    }
    ContinueReadingLocked();
    MaybeFinishLocked();
  }

 private:
  void ContinueReadingLocked() {
    if (finishing_ || reading_ || half_closed_) return;
    if (outstanding_ >= cap_) return;  // flow control: read more once one completes
    reading_ = true;
    StartRead(&request_);
  }

  void HandleLocked(const v1::RenderRequest& request) {
    if (session_ == nullptr) {
      if (request.has_open()) {
        Open(request.open());
      } else if (request.has_resume()) {
        Resume(request.resume());
      } else {
        FinishLocked(grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                                  "frame: the first message must be open or resume"));
      }
      return;
    }
    if (!request.has_frame()) {
      FinishLocked(grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                                request.has_open() ? "open: the session is already open"
                                                   : "resume: the session is already open"));
      return;
    }
    const v1::FrameInput& frame = request.frame();
    std::optional<BreakPoint> break_point;
    {
      std::lock_guard<std::mutex> lock(state_->sessions_mu);
      ++state_->frames_received;
      if (state_->break_on_frame.has_value() &&
          state_->break_on_frame->first == frame.frame_index()) {
        break_point = state_->break_on_frame->second;
        state_->break_on_frame.reset();
      }
    }
    state_->frames_cv.notify_all();
    if (break_point == BreakPoint::kBeforeRender) {
      FinishLocked(
          grpc::Status(grpc::StatusCode::UNAVAILABLE, "fake: stream broken before render"));
      return;
    }
    ++outstanding_;
    {
      std::lock_guard<std::mutex> lock(state_->sessions_mu);
      state_->max_outstanding = std::max(state_->max_outstanding, outstanding_);
    }
    if (break_point == BreakPoint::kAfterRender) {
      RenderLocked(frame, /*send=*/false);
      FinishLocked(grpc::Status(grpc::StatusCode::UNAVAILABLE, "fake: answer lost after render"));
      return;
    }
    if (paused_) {
      held_.push_back(frame);
      return;
    }
    RenderLocked(frame);
  }

  void Open(const v1::OpenSession& open) {
    const FakeRenderServerOptions& options = state_->options;
    {
      std::lock_guard<std::mutex> lock(state_->sessions_mu);
      if (state_->fail_next_open.has_value()) {
        auto [code, message] = *state_->fail_next_open;
        state_->fail_next_open.reset();
        FinishLocked(grpc::Status(static_cast<grpc::StatusCode>(code), message));
        return;
      }
    }
    if (std::find(options.environments.begin(), options.environments.end(), open.environment()) ==
        options.environments.end()) {
      FinishLocked(grpc::Status(
          grpc::StatusCode::NOT_FOUND,
          absl::StrCat("open.environment: unknown environment '", open.environment(), "'")));
      return;
    }
    const uint32_t width = open.width() == 0 ? options.native_size : open.width();
    const uint32_t height = open.height() == 0 ? options.native_size : open.height();
    for (auto [name, value] : {std::pair{"open.width", width}, std::pair{"open.height", height}}) {
      if (value % 8 != 0 || value < options.min_size || value > options.max_size) {
        FinishLocked(
            grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                         absl::StrCat(name, ": must be a multiple of 8 in [", options.min_size,
                                      ", ", options.max_size, "], got ", value)));
        return;
      }
    }
    if (open.steps() > options.max_steps) {
      FinishLocked(grpc::Status(
          grpc::StatusCode::INVALID_ARGUMENT,
          absl::StrCat("open.steps: must be in [1, ", options.max_steps, "], got ", open.steps())));
      return;
    }
    auto session = std::make_shared<FakeSession>();
    if (open.has_keyframe()) {
      absl::StatusOr<ImageF> keyframe =
          DecodeImage(open.keyframe(), 3, width, height, "open.keyframe");
      if (!keyframe.ok()) {
        FinishLocked(grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                                  std::string(keyframe.status().message())));
        return;
      }
      session->previous = std::move(*keyframe);
    }
    v1::SessionSettings& settings = session->settings;
    settings.set_environment(open.environment());
    settings.set_width(width);
    settings.set_height(height);
    settings.set_seed(open.seed() != 0 ? open.seed() : 4242);
    settings.set_steps(open.steps() != 0 ? open.steps() : options.default_steps);
    settings.set_scheduler(open.scheduler() != v1::SCHEDULER_UNSPECIFIED ? open.scheduler()
                                                                         : v1::SCHEDULER_UNIPC);
    settings.set_sky_mode(open.sky_mode() != v1::SKY_MODE_UNSPECIFIED
                              ? open.sky_mode()
                              : v1::SKY_MODE_PREVIOUS_OUTPUT);
    settings.set_output_dtype(open.output_dtype() != v1::DTYPE_UNSPECIFIED ? open.output_dtype()
                                                                           : v1::DTYPE_UINT8);
    settings.set_output_compression(open.output_compression());
    const uint32_t in_flight =
        open.max_frames_in_flight() == 0
            ? options.max_frames_in_flight
            : std::min(open.max_frames_in_flight(), options.max_frames_in_flight);
    settings.set_max_frames_in_flight(in_flight);
    settings.set_started_from_keyframe(open.has_keyframe());
    session->token = RandomHex();
    {
      std::lock_guard<std::mutex> lock(state_->sessions_mu);
      // Adopt the client's routing key as the id (so x-session-id on resume
      // equals it and a hash-based balancer routes both alike).
      session->id = IsSessionIdShape(routing_key_) && state_->sessions.count(routing_key_) == 0
                        ? routing_key_
                        : RandomHex();
      state_->sessions[session->id] = session;
      ++state_->sessions_opened;
      state_->opened_ids.push_back(session->id);
    }
    session_ = session;
    cap_ = static_cast<int>(in_flight);
    v1::RenderResponse response;
    v1::SessionOpened* opened = response.mutable_opened();
    opened->set_session_id(session->id);
    opened->set_resume_token(session->token);
    *opened->mutable_settings() = settings;
    QueueWriteLocked(std::move(response));
  }

  void Resume(const v1::ResumeSession& resume) {
    std::shared_ptr<FakeSession> session;
    {
      std::lock_guard<std::mutex> lock(state_->sessions_mu);
      auto it = state_->sessions.find(resume.session_id());
      if (it != state_->sessions.end()) session = it->second;
    }
    if (session == nullptr) {
      FinishLocked(grpc::Status(
          grpc::StatusCode::NOT_FOUND,
          absl::StrCat("resume.session_id: unknown session '", resume.session_id(), "'")));
      return;
    }
    if (session->token != resume.resume_token()) {
      FinishLocked(
          grpc::Status(grpc::StatusCode::PERMISSION_DENIED, "resume.resume_token: does not match"));
      return;
    }
    if (session->closed) {
      v1::RenderResponse notice;
      notice.mutable_notice()->set_reason(v1::SessionNotice::REASON_CLOSED);
      notice.mutable_notice()->set_message("closed by its client");
      QueueWriteLocked(std::move(notice));
      FinishLocked(grpc::Status(grpc::StatusCode::NOT_FOUND, "resume.session_id: session closed"));
      return;
    }
    {
      std::lock_guard<std::mutex> lock(state_->sessions_mu);
      ++state_->sessions_resumed;
    }
    session_ = session;
    cap_ = static_cast<int>(session->settings.max_frames_in_flight());
    v1::RenderResponse response;
    v1::SessionOpened* opened = response.mutable_opened();
    opened->set_session_id(session->id);
    opened->set_resume_token(session->token);
    *opened->mutable_settings() = session->settings;
    opened->set_resumed(true);
    if (session->last_frame_index.has_value()) {
      opened->set_last_frame_index(*session->last_frame_index);
    }
    QueueWriteLocked(std::move(response));
  }

  // Renders one frame (or rejects it with a FrameError) and queues the answer.
  void RenderLocked(const v1::FrameInput& frame, bool send = true) {
    --outstanding_;
    FakeSession& session = *session_;
    const v1::SessionSettings& settings = session.settings;
    v1::RenderResponse response;
    auto reject = [&](int code, const std::string& message) {
      v1::FrameError* error = response.mutable_frame_error();
      error->set_frame_index(frame.frame_index());
      error->set_code(code);
      error->set_message(message);
    };
    if (session.last_frame_index.has_value() && frame.frame_index() <= *session.last_frame_index) {
      reject(
          grpc::StatusCode::FAILED_PRECONDITION,
          absl::StrCat("frame.frame_index: ", frame.frame_index(),
                       " must be greater than the previous frame's ", *session.last_frame_index));
    } else {
      const uint32_t w = settings.width(), h = settings.height();
      absl::StatusOr<ImageF> basecolor =
          DecodeImage(frame.gbuffer().basecolor(), 3, w, h, "frame.gbuffer.basecolor");
      absl::StatusOr<ImageF> normals =
          DecodeImage(frame.gbuffer().normals(), 3, w, h, "frame.gbuffer.normals");
      absl::StatusOr<ImageF> depth =
          DecodeImage(frame.gbuffer().depth(), 1, w, h, "frame.gbuffer.depth");
      absl::StatusOr<ImageF> roughness =
          DecodeImage(frame.gbuffer().roughness(), 1, w, h, "frame.gbuffer.roughness");
      absl::Status bad;
      for (const absl::Status& s :
           {basecolor.status(), normals.status(), depth.status(), roughness.status()}) {
        if (bad.ok() && !s.ok()) bad = s;
      }
      if (bad.ok() && frame.gbuffer().has_metallic()) {
        bad = DecodeImage(frame.gbuffer().metallic(), 1, w, h, "frame.gbuffer.metallic").status();
      }
      ImageF previous = session.previous;
      if (bad.ok() && frame.has_keyframe()) {
        absl::StatusOr<ImageF> keyframe = DecodeImage(frame.keyframe(), 3, w, h, "frame.keyframe");
        if (keyframe.ok()) {
          previous = std::move(*keyframe);
        } else {
          bad = keyframe.status();
        }
      }
      if (!bad.ok()) {
        reject(static_cast<int>(bad.code()), std::string(bad.message()));
      } else {
        const ImageF out = FakeRenderServer::Render(*basecolor, *depth, previous);
        ImageF seen;
        v1::RenderedFrame* rendered = response.mutable_frame();
        rendered->set_frame_index(frame.frame_index());
        *rendered->mutable_image() =
            EncodeOutput(out, settings.output_dtype(), settings.output_compression(), &seen);
        rendered->mutable_timings()->set_total_ms(1.0);
        rendered->mutable_timings()->set_batch_size(1);
        {
          std::lock_guard<std::mutex> lock(state_->sessions_mu);
          session.previous = std::move(seen);
          session.last_frame_index = frame.frame_index();
          ++state_->frames_rendered;
        }
      }
    }
    if (send) QueueWriteLocked(std::move(response));
  }

  void QueueWriteLocked(v1::RenderResponse response) {
    if (finishing_) return;
    writes_.push_back(std::move(response));
    StartNextWriteLocked();
  }

  void StartNextWriteLocked() {
    if (writing_) return;
    if (writes_.empty()) {
      if (finishing_ && !finished_) {
        finished_ = true;
        Finish(*finish_status_);
      }
      return;
    }
    writing_ = true;
    StartWrite(&writes_.front());
  }

  // A half-closed stream finishes once every frame is answered; the session
  // is then closed.
  void MaybeFinishLocked() {
    if (!half_closed_ || finishing_ || !held_.empty() || outstanding_ > 0) return;
    if (session_ != nullptr) {
      std::lock_guard<std::mutex> lock(state_->sessions_mu);
      session_->closed = true;
    }
    FinishLocked(grpc::Status::OK);
  }

  // Finishes after the writes already queued (a Finish must not overtake an
  // outstanding write).
  void FinishLocked(grpc::Status status) {
    if (finishing_) return;
    finishing_ = true;
    finish_status_ = std::move(status);
    StartNextWriteLocked();
  }

  const std::shared_ptr<State> state_;
  std::mutex mu_;
  std::string routing_key_;
  v1::RenderRequest request_;
  std::deque<v1::RenderResponse> writes_;
  std::deque<v1::FrameInput> held_;
  std::shared_ptr<FakeSession> session_;
  int outstanding_ = 0;
  int cap_ = 1;
  bool paused_ = false;
  bool reading_ = false;
  bool writing_ = false;
  bool half_closed_ = false;
  bool finishing_ = false;
  bool finished_ = false;
  std::optional<grpc::Status> finish_status_;
};

class FakeService final : public v1::FrameDiffuser::CallbackService {
 public:
  explicit FakeService(std::shared_ptr<State> state) : state_(std::move(state)) {}

  grpc::ServerUnaryReactor* ListEnvironments(grpc::CallbackServerContext* context,
                                             const v1::ListEnvironmentsRequest*,
                                             v1::ListEnvironmentsResponse* response) override {
    grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
    const FakeRenderServerOptions& options = state_->options;
    std::string authorization;
    for (const auto& [key, value] : context->client_metadata()) {
      if (key == "authorization") authorization.assign(value.data(), value.size());
    }
    {
      std::lock_guard<std::mutex> lock(state_->sessions_mu);
      state_->authorization.push_back(authorization);
    }
    if (!options.required_token.empty() && authorization != "Bearer " + options.required_token) {
      reactor->Finish(
          grpc::Status(grpc::StatusCode::UNAUTHENTICATED, "missing or wrong bearer token"));
      return reactor;
    }
    for (const std::string& name : options.environments) {
      v1::Environment* environment = response->add_environments();
      environment->set_name(name);
      environment->set_description("fake environment for SDK tests");
      environment->set_prompt("a fake prompt");
      environment->set_native_width(options.native_size);
      environment->set_native_height(options.native_size);
      environment->set_default_steps(options.default_steps);
      environment->set_max_steps(options.max_steps);
      environment->set_default_scheduler(v1::SCHEDULER_UNIPC);
      environment->set_default_sky_mode(v1::SKY_MODE_PREVIOUS_OUTPUT);
      environment->set_readiness(v1::READINESS_READY);
      environment->set_min_size(options.min_size);
      environment->set_max_size(options.max_size);
    }
    reactor->Finish(grpc::Status::OK);
    return reactor;
  }

  grpc::ServerBidiReactor<v1::RenderRequest, v1::RenderResponse>* Render(
      grpc::CallbackServerContext* context) override {
    return new RenderStream(state_, context);
  }

 private:
  std::shared_ptr<State> state_;
};

}  // namespace

FakeRenderServer::FakeRenderServer(FakeRenderServerOptions options)
    : state_(std::make_shared<State>()) {
  state_->options = std::move(options);
}

FakeRenderServer::~FakeRenderServer() { Stop(); }

absl::Status FakeRenderServer::Start() {
  std::lock_guard<std::mutex> lock(state_->server_mu);
  if (state_->server != nullptr) return absl::OkStatus();
  grpc::EnableDefaultHealthCheckService(true);
  std::shared_ptr<grpc::ServerCredentials> credentials = grpc::InsecureServerCredentials();
  const FakeRenderServerOptions& options = state_->options;
  if (!options.tls_cert_pem.empty() && !options.tls_key_pem.empty()) {
    grpc::SslServerCredentialsOptions ssl;
    ssl.pem_key_cert_pairs.push_back({options.tls_key_pem, options.tls_cert_pem});
    credentials = grpc::SslServerCredentials(ssl);
  }
  auto service = std::make_unique<FakeService>(state_);
  grpc::ServerBuilder builder;
  int selected = 0;
  builder.AddListeningPort(absl::StrCat("127.0.0.1:", state_->port), credentials, &selected);
  builder.RegisterService(service.get());
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  if (server == nullptr || selected == 0) {
    return absl::InternalError(
        absl::StrCat("fake server: cannot listen on 127.0.0.1:", state_->port));
  }
  server->GetHealthCheckService()->SetServingStatus("framediffuser.v1.FrameDiffuser", true);
  state_->port = selected;
  state_->service = std::move(service);
  state_->server = std::move(server);
  return absl::OkStatus();
}

void FakeRenderServer::Stop() {
  std::lock_guard<std::mutex> lock(state_->server_mu);
  if (state_->server == nullptr) return;
  // An immediate deadline: in-flight calls are cancelled, like a crash.
  state_->server->Shutdown(std::chrono::system_clock::now());
  state_->server->Wait();
  state_->server.reset();
  state_->service.reset();
  if (!state_->options.keep_sessions_across_restart) {
    std::lock_guard<std::mutex> sessions(state_->sessions_mu);
    state_->sessions.clear();
  }
}

int FakeRenderServer::port() const {
  std::lock_guard<std::mutex> lock(state_->server_mu);
  return state_->port;
}

void FakeRenderServer::SetPortForTesting(int port) {
  std::lock_guard<std::mutex> lock(state_->server_mu);
  state_->port = port;
}

std::string FakeRenderServer::address() const { return absl::StrCat("127.0.0.1:", port()); }

void FakeRenderServer::BreakStreams() {
  std::lock_guard<std::mutex> registry(state_->registry_mu);
  for (RenderStream* stream : state_->streams) {
    stream->Break(grpc::Status(grpc::StatusCode::UNAVAILABLE, "fake: stream broken"), std::nullopt);
  }
}

void FakeRenderServer::Drain() {
  {
    std::lock_guard<std::mutex> registry(state_->registry_mu);
    v1::SessionNotice notice;
    notice.set_reason(v1::SessionNotice::REASON_DRAINING);
    notice.set_message("fake: shutting down");
    for (RenderStream* stream : state_->streams) {
      stream->Break(grpc::Status(grpc::StatusCode::UNAVAILABLE, "fake: draining"), notice);
    }
  }
  std::lock_guard<std::mutex> lock(state_->sessions_mu);
  state_->sessions.clear();
}

void FakeRenderServer::BreakOnFrame(uint64_t frame_index, BreakPoint point) {
  std::lock_guard<std::mutex> lock(state_->sessions_mu);
  state_->break_on_frame = std::make_pair(frame_index, point);
}

void FakeRenderServer::FailNextOpen(int code, const std::string& message) {
  std::lock_guard<std::mutex> lock(state_->sessions_mu);
  state_->fail_next_open = std::make_pair(code, message);
}

void FakeRenderServer::PauseRendering() {
  std::lock_guard<std::mutex> registry(state_->registry_mu);
  state_->paused = true;
  for (RenderStream* stream : state_->streams) stream->SetPaused(true);
}

void FakeRenderServer::ResumeRendering() {
  std::lock_guard<std::mutex> registry(state_->registry_mu);
  state_->paused = false;
  for (RenderStream* stream : state_->streams) stream->SetPaused(false);
}

bool FakeRenderServer::WaitForFramesReceived(int count, absl::Duration timeout) {
  std::unique_lock<std::mutex> lock(state_->sessions_mu);
  return state_->frames_cv.wait_for(lock, absl::ToChronoNanoseconds(timeout),
                                    [&] { return state_->frames_received >= count; });
}

int FakeRenderServer::sessions_opened() const {
  std::lock_guard<std::mutex> lock(state_->sessions_mu);
  return state_->sessions_opened;
}
int FakeRenderServer::sessions_resumed() const {
  std::lock_guard<std::mutex> lock(state_->sessions_mu);
  return state_->sessions_resumed;
}
int FakeRenderServer::frames_received() const {
  std::lock_guard<std::mutex> lock(state_->sessions_mu);
  return state_->frames_received;
}
int FakeRenderServer::frames_rendered() const {
  std::lock_guard<std::mutex> lock(state_->sessions_mu);
  return state_->frames_rendered;
}
int FakeRenderServer::max_outstanding_frames() const {
  std::lock_guard<std::mutex> lock(state_->sessions_mu);
  return state_->max_outstanding;
}
std::vector<std::string> FakeRenderServer::x_session_id_headers() const {
  std::lock_guard<std::mutex> lock(state_->sessions_mu);
  return state_->x_session_ids;
}
std::vector<std::string> FakeRenderServer::opened_session_ids() const {
  std::lock_guard<std::mutex> lock(state_->sessions_mu);
  return state_->opened_ids;
}
std::vector<std::string> FakeRenderServer::authorization_headers() const {
  std::lock_guard<std::mutex> lock(state_->sessions_mu);
  return state_->authorization;
}

client::ImageF FakeRenderServer::Render(const client::ImageF& basecolor,
                                        const client::ImageF& depth,
                                        const client::ImageF& previous) {
  ImageF out(basecolor.width, basecolor.height, 3);
  for (int y = 0; y < out.height; ++y) {
    for (int x = 0; x < out.width; ++x) {
      for (int c = 0; c < 3; ++c) {
        const float prev = previous.empty() ? 0.0f : previous.at(x, y, c);
        const float v = (2.0f * basecolor.at(x, y, c) + prev + depth.at(x, y, 0)) / 4.0f;
        out.at(x, y, c) = std::clamp(v, 0.0f, 1.0f);
      }
    }
  }
  return out;
}

}  // namespace fd::testing
