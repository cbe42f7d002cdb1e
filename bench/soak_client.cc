#include "bench/soak_client.h"

#include <grpc/grpc.h>

#include <algorithm>
#include <chrono>
#include <cstring>
#include <deque>
#include <optional>
#include <random>
#include <thread>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/string_view.h"
#include "base/status_macros.h"

namespace fd::bench {
namespace {

using Clock = std::chrono::steady_clock;
using Stream = grpc::ClientReaderWriter<v1::RenderRequest, v1::RenderResponse>;

// Streams end on their own long before this; it only turns a hung server
// into a reported failure instead of a hung soak run.
constexpr absl::Duration kStreamGrace = absl::Seconds(120);

// SplitMix64's output function: every seed of a run derives from run_seed.
uint64_t Mix64(uint64_t z) {
  z += 0x9e3779b97f4a7c15ULL;
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
  return z ^ (z >> 31);
}

uint64_t Fnv1a(absl::string_view data) {
  uint64_t hash = 0xcbf29ce484222325ULL;
  for (unsigned char byte : data) hash = (hash ^ byte) * 0x100000001b3ULL;
  return hash;
}

// A uint8 image of pseudo-random bytes drawn from `seed`.
v1::Image NoiseImage(uint32_t size, uint32_t channels, uint64_t seed) {
  v1::Image image;
  image.set_width(size);
  image.set_height(size);
  image.set_channels(channels);
  image.set_dtype(v1::DTYPE_UINT8);
  std::string data(static_cast<size_t>(size) * size * channels, '\0');
  uint64_t state = seed;
  for (size_t i = 0; i < data.size(); i += 8) {
    const uint64_t bits = Mix64(state++);
    std::memcpy(&data[i], &bits, std::min<size_t>(8, data.size() - i));
  }
  image.set_data(std::move(data));
  return image;
}

// The G-buffer of a frame is a function of its input seed only, so the
// replay can make it again.
v1::RenderRequest MakeFrame(uint32_t size, uint64_t frame_index, uint64_t input_seed) {
  v1::RenderRequest request;
  v1::FrameInput* frame = request.mutable_frame();
  frame->set_frame_index(frame_index);
  v1::GBuffer* gbuffer = frame->mutable_gbuffer();
  *gbuffer->mutable_basecolor() = NoiseImage(size, 3, Mix64(input_seed ^ 1));
  *gbuffer->mutable_normals() = NoiseImage(size, 3, Mix64(input_seed ^ 2));
  *gbuffer->mutable_depth() = NoiseImage(size, 1, Mix64(input_seed ^ 3));
  *gbuffer->mutable_roughness() = NoiseImage(size, 1, Mix64(input_seed ^ 4));
  *gbuffer->mutable_metallic() = NoiseImage(size, 1, Mix64(input_seed ^ 5));
  return request;
}

// A frame the server must refuse with INVALID_ARGUMENT (FrameError), one of
// several defects a buggy client makes.
v1::RenderRequest MakeInvalidFrame(uint32_t size, uint64_t frame_index, uint64_t input_seed,
                                   int defect) {
  v1::RenderRequest request = MakeFrame(size, frame_index, input_seed);
  v1::GBuffer* gbuffer = request.mutable_frame()->mutable_gbuffer();
  switch (defect % 4) {
    case 0:
      gbuffer->clear_normals();  // a required plane is missing
      break;
    case 1:
      gbuffer->clear_depth();
      break;
    case 2:
      *gbuffer->mutable_roughness() = NoiseImage(size, 3, input_seed);  // 3 channels, not 1
      break;
    default:
      gbuffer->mutable_basecolor()->mutable_data()->resize(7);  // byte length mismatch
      break;
  }
  return request;
}

std::string Describe(const v1::RenderResponse& response) {
  if (response.has_frame()) return absl::StrCat("RenderedFrame ", response.frame().frame_index());
  if (response.has_frame_error()) {
    return absl::StrCat("FrameError ", response.frame_error().frame_index(), " (code ",
                        response.frame_error().code(), ": ", response.frame_error().message(), ")");
  }
  if (response.has_opened()) return "SessionOpened";
  if (response.has_notice()) {
    return absl::StrCat("SessionNotice ",
                        v1::SessionNotice::Reason_Name(response.notice().reason()), " (",
                        response.notice().message(), ")");
  }
  return "an empty RenderResponse";
}

std::string Describe(const grpc::Status& status) {
  return absl::StrCat("status ", static_cast<int>(status.error_code()), " '",
                      status.error_message(), "'");
}

v1::RenderRequest OpenRequest(const SoakClientOptions& options, uint64_t seed,
                              uint32_t max_frames_in_flight) {
  v1::RenderRequest request;
  v1::OpenSession* open = request.mutable_open();
  open->set_environment(options.environment);
  open->set_width(options.size);
  open->set_height(options.size);
  open->set_steps(options.steps);
  open->set_seed(seed);
  open->set_max_frames_in_flight(max_frames_in_flight);
  return request;
}

absl::Status CheckOpened(const v1::RenderResponse& response, const SoakClientOptions& options,
                         uint64_t seed) {
  if (!response.has_opened()) {
    return absl::InternalError(
        absl::StrCat("open: expected SessionOpened, got ", Describe(response)));
  }
  const v1::SessionSettings& settings = response.opened().settings();
  if (response.opened().resumed() || settings.seed() != seed || settings.width() != options.size ||
      settings.height() != options.size || settings.steps() != options.steps) {
    return absl::InternalError(
        absl::StrCat("open: SessionOpened does not match the request: ", response.DebugString()));
  }
  return absl::OkStatus();
}

absl::Status CheckImage(const v1::Image& image, const SoakClientOptions& options) {
  const size_t expected = static_cast<size_t>(options.size) * options.size * 3;
  if (image.width() != options.size || image.height() != options.size || image.channels() != 3 ||
      image.dtype() != v1::DTYPE_UINT8 || image.compression() != v1::COMPRESSION_NONE ||
      image.data().size() != expected) {
    return absl::InternalError(absl::StrCat("rendered image is ", image.width(), "x",
                                            image.height(), "x", image.channels(), " dtype ",
                                            image.dtype(), ", ", image.data().size(), " bytes"));
  }
  return absl::OkStatus();
}

// A frame written and not yet answered.
struct Sent {
  uint64_t index = 0;
  uint64_t input_seed = 0;
  bool valid = true;
  Clock::time_point written;
  bool timed = false;  // its latency counts (normal segments only)
};

// A valid frame to send again after a resume.
struct ToSend {
  uint64_t index = 0;
  uint64_t input_seed = 0;
};

class SoakClient {
 public:
  SoakClient(int client, const SoakClientOptions& options, ClientResult* result)
      : client_(client),
        options_(options),
        result_(result),
        rng_(Mix64(options.run_seed ^ (static_cast<uint64_t>(client) << 32))) {}

  ~SoakClient() { Abandon(); }

  absl::Status Run() {
    channel_ = NewChannel(options_.target);
    stub_ = v1::FrameDiffuser::NewStub(channel_);
    FD_RETURN_IF_ERROR(OpenSession());
    while (absl::Now() < options_.deadline) {
      // Weights: mostly normal streaming; every other behaviour often
      // enough that each client meets each several times a minute.
      const int pick = Uniform(0, 99);
      if (pick < 45) {
        FD_RETURN_IF_ERROR(Normal());
      } else if (pick < 57) {
        FD_RETURN_IF_ERROR(Slow());
      } else if (pick < 72) {
        FD_RETURN_IF_ERROR(Invalid());
      } else if (pick < 81) {
        FD_RETURN_IF_ERROR(CancelAndResume(/*new_channel=*/false));
      } else if (pick < 88) {
        FD_RETURN_IF_ERROR(CancelAndResume(/*new_channel=*/true));
      } else if (pick < 93) {
        FD_RETURN_IF_ERROR(Takeover());
      } else {
        FD_RETURN_IF_ERROR(CloseSession());
        FD_RETURN_IF_ERROR(OpenSession());
      }
    }
    return CloseSession();
  }

  std::string Where() const {
    return absl::StrCat("client ", client_, ", session ",
                        record_index_ < result_->sessions.size()
                            ? result_->sessions[record_index_].session_id
                            : std::string("(none)"));
  }

 private:
  int Uniform(int lo, int hi) { return std::uniform_int_distribution<int>(lo, hi)(rng_); }
  SessionRecord& record() { return result_->sessions[record_index_]; }
  ClientCounts& counts() { return result_->counts; }

  // ---- Streams.

  void StartStream(bool resuming) {
    stream_.reset();
    context_ = std::make_unique<grpc::ClientContext>();
    context_->set_deadline(absl::ToChronoTime(options_.deadline + kStreamGrace));
    // A session-sticky balancer routes a resume by this key (proto).
    if (resuming) context_->AddMetadata("x-session-id", record().session_id);
    stream_ = stub_->Render(context_.get());
  }

  // The stream ended where it must not: drains it and says how it ended.
  absl::Status Ended(absl::string_view doing) {
    std::string seen;
    v1::RenderResponse response;
    while (stream_->Read(&response)) {
      absl::StrAppend(&seen, seen.empty() ? "" : ", ", Describe(response));
    }
    const grpc::Status status = stream_->Finish();
    stream_.reset();
    return absl::InternalError(absl::StrCat("the stream ended while ", doing, ": ",
                                            Describe(status),
                                            seen.empty() ? "" : "; messages after: ", seen));
  }

  // On failure: cancel whatever stream is open, so nothing outlives Run().
  void Abandon() {
    if (stream_ == nullptr) return;
    context_->TryCancel();
    v1::RenderResponse response;
    while (stream_->Read(&response)) {
    }
    stream_->Finish();
    stream_.reset();
  }

  // ---- Frames.

  uint64_t InputSeed(uint64_t index) const {
    return Mix64(Mix64(Mix64(options_.run_seed) ^ static_cast<uint64_t>(client_)) ^
                 (static_cast<uint64_t>(session_ordinal_) << 40) ^ index);
  }

  // The next valid frame: a re-send first, then the retry of an invalid
  // frame's index, then a new index (sometimes after a gap, which the proto
  // allows).
  absl::Status WriteValid(bool timed) {
    ToSend frame;
    if (!resend_.empty()) {
      frame = resend_.front();
      resend_.pop_front();
      ++counts().frames_resent;
    } else {
      if (retry_index_.has_value()) {
        frame.index = *retry_index_;
        retry_index_.reset();
      } else {
        last_index_ += Uniform(0, 9) == 0 ? Uniform(2, 4) : 1;
        frame.index = last_index_;
      }
      frame.input_seed = InputSeed(frame.index);
    }
    const Clock::time_point now = Clock::now();
    if (!stream_->Write(MakeFrame(options_.size, frame.index, frame.input_seed))) {
      return Ended(absl::StrCat("writing frame ", frame.index));
    }
    ++counts().frames_written;
    in_flight_.push_back(Sent{frame.index, frame.input_seed, true, now, timed});
    return absl::OkStatus();
  }

  // An invalid frame at a new index; half the time the next valid frame
  // retries that index (the session is unchanged by a refused frame).
  absl::Status WriteInvalid() {
    last_index_ += 1;
    const uint64_t index = last_index_;
    if (Uniform(0, 1) == 0) retry_index_ = index;
    if (!stream_->Write(MakeInvalidFrame(options_.size, index, InputSeed(index), Uniform(0, 3)))) {
      return Ended(absl::StrCat("writing invalid frame ", index));
    }
    ++counts().frames_written;
    in_flight_.push_back(Sent{index, 0, false, Clock::now(), false});
    return absl::OkStatus();
  }

  absl::Status ReadAnswer() {
    if (in_flight_.empty()) return absl::InternalError("bug: reading with no frame in flight");
    v1::RenderResponse response;
    if (!stream_->Read(&response)) {
      return Ended(absl::StrCat("waiting for the answer to frame ", in_flight_.front().index));
    }
    return CheckAnswer(response);
  }

  // `response` must answer the oldest frame in flight.
  absl::Status CheckAnswer(const v1::RenderResponse& response) {
    if (in_flight_.empty()) {
      return absl::InternalError(
          absl::StrCat("got ", Describe(response), " with no frame in flight"));
    }
    const Sent sent = in_flight_.front();
    if (response.has_frame()) {
      if (response.frame().frame_index() != sent.index) {
        return absl::InternalError(absl::StrCat("answers out of order: got ", Describe(response),
                                                ", expected the answer to frame ", sent.index));
      }
      if (!sent.valid) {
        return absl::InternalError(absl::StrCat("invalid frame ", sent.index, " was rendered"));
      }
      FD_RETURN_IF_ERROR(CheckImage(response.frame().image(), options_));
      record().rendered.push_back(
          RenderedFrame{sent.index, sent.input_seed, Fnv1a(response.frame().image().data())});
      last_rendered_ = sent.index;
      ++counts().frames_answered;
      if (sent.timed) {
        result_->latency_ms.push_back(
            std::chrono::duration<double, std::milli>(Clock::now() - sent.written).count());
      }
    } else if (response.has_frame_error()) {
      if (response.frame_error().frame_index() != sent.index) {
        return absl::InternalError(absl::StrCat("answers out of order: got ", Describe(response),
                                                ", expected the answer to frame ", sent.index));
      }
      if (sent.valid) {
        return absl::InternalError(absl::StrCat("a valid frame was refused: ", Describe(response)));
      }
      if (response.frame_error().code() != static_cast<int>(grpc::StatusCode::INVALID_ARGUMENT)) {
        return absl::InternalError(
            absl::StrCat("invalid frame refused with the wrong code: ", Describe(response)));
      }
      ++counts().frame_errors;
    } else {
      return absl::InternalError(
          absl::StrCat("expected the answer to frame ", sent.index, ", got ", Describe(response)));
    }
    in_flight_.pop_front();
    return absl::OkStatus();
  }

  // Writes `frames` valid frames, keeping at most `window` in flight; reads
  // after a pause of up to `read_delay` ms when the window is full.
  absl::Status Pump(int frames, size_t window, bool timed, int read_delay_ms) {
    for (int written = 0; written < frames;) {
      if (in_flight_.size() < window) {
        FD_RETURN_IF_ERROR(WriteValid(timed));
        ++written;
      } else {
        // The slow reader is the behaviour under test, not synchronisation.
        if (read_delay_ms > 0)
          std::this_thread::sleep_for(std::chrono::milliseconds(Uniform(1, read_delay_ms)));
        FD_RETURN_IF_ERROR(ReadAnswer());
      }
    }
    return absl::OkStatus();
  }

  absl::Status Drain(size_t keep) {
    while (in_flight_.size() > keep) FD_RETURN_IF_ERROR(ReadAnswer());
    return absl::OkStatus();
  }

  // ---- Behaviours.

  absl::Status Normal() {
    const size_t window = static_cast<size_t>(Uniform(1, static_cast<int>(window_cap_)));
    FD_RETURN_IF_ERROR(Drain(window));
    FD_RETURN_IF_ERROR(Pump(Uniform(4, 16), window, /*timed=*/true, 0));
    // Sometimes in lock step at the end, so that the server sees idle gaps.
    return Uniform(0, 2) == 0 ? Drain(0) : absl::OkStatus();
  }

  // Writes ahead of the session's max_frames_in_flight and reads slowly:
  // the server stops reading and HTTP/2 flow control holds the client back.
  absl::Status Slow() {
    ++counts().slow_segments;
    return Pump(Uniform(3, 8), window_cap_ + 2, /*timed=*/false, 25);
  }

  // Invalid frames between valid ones, written without waiting: each
  // FrameError must come in its frame's place.
  absl::Status Invalid() {
    FD_RETURN_IF_ERROR(Drain(window_cap_));
    FD_RETURN_IF_ERROR(Pump(Uniform(0, 2), window_cap_ + 1, false, 0));
    if (resend_.empty()) {
      FD_RETURN_IF_ERROR(Drain(window_cap_));
      FD_RETURN_IF_ERROR(WriteInvalid());
    }
    return Pump(Uniform(1, 3), window_cap_ + 1, false, 0);
  }

  // Breaks the stream with frames in flight and resumes the session, on the
  // same channel or on a new one (a client that lost its connection).
  absl::Status CancelAndResume(bool new_channel) {
    ++(new_channel ? counts().reconnects : counts().cancels);
    FD_RETURN_IF_ERROR(Drain(window_cap_));
    FD_RETURN_IF_ERROR(
        Pump(Uniform(1, static_cast<int>(window_cap_) + 1), window_cap_ + 1, false, 0));
    if (Uniform(0, 1) == 0 && !in_flight_.empty()) {
      FD_RETURN_IF_ERROR(Drain(in_flight_.size() - 1));
    }
    context_->TryCancel();
    // Answers already on their way may still arrive, in order.
    v1::RenderResponse response;
    while (stream_->Read(&response)) FD_RETURN_IF_ERROR(CheckAnswer(response));
    const grpc::Status status = stream_->Finish();
    stream_.reset();
    if (status.error_code() != grpc::StatusCode::CANCELLED) {
      return absl::InternalError(
          absl::StrCat("a cancelled stream ended with ", Describe(status), ", not CANCELLED"));
    }
    if (new_channel) {
      channel_ = NewChannel(options_.target);
      stub_ = v1::FrameDiffuser::NewStub(channel_);
    }
    StartStream(/*resuming=*/true);
    return Resume();
  }

  // Resumes on a second stream while the first is still open: the first
  // ends with ABORTED after the answers it already sent.
  absl::Status Takeover() {
    ++counts().takeovers;
    FD_RETURN_IF_ERROR(Drain(window_cap_));
    FD_RETURN_IF_ERROR(Pump(Uniform(1, static_cast<int>(window_cap_)), window_cap_, false, 0));
    // The old call lives on its channel until it is finished.
    std::shared_ptr<grpc::Channel> old_channel = channel_;
    std::unique_ptr<v1::FrameDiffuser::Stub> old_stub = std::move(stub_);
    std::unique_ptr<grpc::ClientContext> old_context = std::move(context_);
    std::unique_ptr<Stream> old_stream = std::move(stream_);
    stub_ = v1::FrameDiffuser::NewStub(channel_);
    if (Uniform(0, 1) == 0) {
      channel_ = NewChannel(options_.target);
      stub_ = v1::FrameDiffuser::NewStub(channel_);
    }
    StartStream(/*resuming=*/true);
    if (!stream_->Write(ResumeRequest())) return Ended("writing the takeover's resume");
    v1::RenderResponse response;
    while (old_stream->Read(&response)) FD_RETURN_IF_ERROR(CheckAnswer(response));
    const grpc::Status status = old_stream->Finish();
    if (status.error_code() != grpc::StatusCode::ABORTED) {
      return absl::InternalError(
          absl::StrCat("the stream taken over ended with ", Describe(status), ", not ABORTED"));
    }
    return ReadResumeAnswer();
  }

  v1::RenderRequest ResumeRequest() {
    v1::RenderRequest request;
    request.mutable_resume()->set_session_id(record().session_id);
    request.mutable_resume()->set_resume_token(token_);
    return request;
  }

  absl::Status Resume() {
    if (!stream_->Write(ResumeRequest())) return Ended("writing ResumeSession");
    return ReadResumeAnswer();
  }

  absl::Status ReadResumeAnswer() {
    v1::RenderResponse response;
    if (!stream_->Read(&response)) return Ended("waiting for the resume's SessionOpened");
    if (!response.has_opened() || !response.opened().resumed() ||
        response.opened().session_id() != record().session_id) {
      return absl::InternalError(
          absl::StrCat("resume answered with ", Describe(response), " ", response.DebugString()));
    }
    std::optional<uint64_t> last;
    if (response.opened().has_last_frame_index()) last = response.opened().last_frame_index();
    return Reconcile(last);
  }

  // What the resume's last_frame_index means for the frames in flight when
  // the stream broke: the valid ones up to it were rendered (their answers
  // are lost), the ones after it were dropped and are sent again.
  absl::Status Reconcile(std::optional<uint64_t> last) {
    auto text = [](std::optional<uint64_t> v) {
      return v.has_value() ? absl::StrCat(*v) : std::string("(none)");
    };
    if (last_rendered_.has_value() && (!last.has_value() || *last < *last_rendered_)) {
      return absl::InternalError(absl::StrCat("resume: last_frame_index ", text(last),
                                              " is before frame ", *last_rendered_,
                                              ", which was answered"));
    }
    std::deque<ToSend> again;
    for (const Sent& sent : in_flight_) {
      if (!sent.valid) continue;  // refused or dropped: either way not rendered
      if (last.has_value() && sent.index <= *last) {
        record().rendered.push_back(RenderedFrame{sent.index, sent.input_seed, std::nullopt});
        last_rendered_ = sent.index;
        ++counts().answers_lost;
      } else {
        again.push_back(ToSend{sent.index, sent.input_seed});
      }
    }
    if (last != last_rendered_) {
      return absl::InternalError(absl::StrCat(
          "resume: last_frame_index ", text(last),
          " is no frame this session sent (last rendered: ", text(last_rendered_), ")"));
    }
    in_flight_.clear();
    again.insert(again.end(), resend_.begin(), resend_.end());
    resend_ = std::move(again);
    return absl::OkStatus();
  }

  absl::Status OpenSession() {
    ++session_ordinal_;
    const uint64_t seed = Mix64(options_.run_seed ^ (static_cast<uint64_t>(client_) << 32) ^
                                static_cast<uint64_t>(session_ordinal_)) |
                          1;  // 0 would ask the server for a random seed
    window_cap_ = static_cast<size_t>(Uniform(1, static_cast<int>(options_.max_frames_in_flight)));
    in_flight_.clear();
    resend_.clear();
    retry_index_.reset();
    last_rendered_.reset();
    last_index_ = static_cast<uint64_t>(Uniform(0, 99));
    record_index_ = result_->sessions.size();  // (none) until opened
    StartStream(/*resuming=*/false);
    if (!stream_->Write(OpenRequest(options_, seed, static_cast<uint32_t>(window_cap_)))) {
      return Ended("writing OpenSession");
    }
    v1::RenderResponse response;
    if (!stream_->Read(&response)) return Ended("waiting for SessionOpened");
    FD_RETURN_IF_ERROR(CheckOpened(response, options_, seed));
    token_ = response.opened().resume_token();
    result_->sessions.push_back(SessionRecord{response.opened().session_id(), client_, seed, {}});
    ++counts().sessions_opened;
    return absl::OkStatus();
  }

  // Sends the frames still owed, half-closes, and expects every answer and
  // OK; sometimes checks that the closed session cannot be resumed.
  absl::Status CloseSession() {
    while (!resend_.empty()) {
      if (in_flight_.size() < window_cap_) {
        FD_RETURN_IF_ERROR(WriteValid(false));
      } else {
        FD_RETURN_IF_ERROR(ReadAnswer());
      }
    }
    stream_->WritesDone();
    FD_RETURN_IF_ERROR(Drain(0));
    v1::RenderResponse response;
    if (stream_->Read(&response)) {
      return absl::InternalError(
          absl::StrCat("after a half-close and the last answer: ", Describe(response)));
    }
    const grpc::Status status = stream_->Finish();
    stream_.reset();
    if (!status.ok()) {
      return absl::InternalError(
          absl::StrCat("a half-closed stream ended with ", Describe(status), ", not OK"));
    }
    ++counts().sessions_closed;
    if (Uniform(0, 3) != 0) return absl::OkStatus();
    // The proto: resuming a closed session gets a CLOSED notice, then NOT_FOUND.
    StartStream(/*resuming=*/true);
    if (!stream_->Write(ResumeRequest())) return Ended("resuming a closed session");
    const bool got = stream_->Read(&response);
    const bool got_more = got && stream_->Read(&response);
    const grpc::Status refused = stream_->Finish();
    stream_.reset();
    if (!got || got_more || !response.has_notice() ||
        response.notice().reason() != v1::SessionNotice::REASON_CLOSED ||
        refused.error_code() != grpc::StatusCode::NOT_FOUND) {
      return absl::InternalError(
          absl::StrCat("resuming the closed session: ", got ? Describe(response) : "no message",
                       got_more ? " and more" : "", ", ", Describe(refused),
                       "; expected a CLOSED notice and NOT_FOUND"));
    }
    ++counts().closed_resume_checks;
    return absl::OkStatus();
  }

  const int client_;
  const SoakClientOptions& options_;
  ClientResult* const result_;
  std::mt19937_64 rng_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::FrameDiffuser::Stub> stub_;
  std::unique_ptr<grpc::ClientContext> context_;
  std::unique_ptr<Stream> stream_;

  // The current session.
  int session_ordinal_ = 0;
  size_t record_index_ = static_cast<size_t>(-1);
  std::string token_;
  size_t window_cap_ = 1;    // its max_frames_in_flight
  uint64_t last_index_ = 0;  // highest frame index used so far
  std::optional<uint64_t> retry_index_;
  std::optional<uint64_t> last_rendered_;  // answered, or counted by a resume
  std::deque<Sent> in_flight_;
  std::deque<ToSend> resend_;
};

}  // namespace

void ClientCounts::Add(const ClientCounts& o) {
  sessions_opened += o.sessions_opened;
  sessions_closed += o.sessions_closed;
  frames_written += o.frames_written;
  frames_answered += o.frames_answered;
  frame_errors += o.frame_errors;
  answers_lost += o.answers_lost;
  frames_resent += o.frames_resent;
  cancels += o.cancels;
  reconnects += o.reconnects;
  takeovers += o.takeovers;
  slow_segments += o.slow_segments;
  closed_resume_checks += o.closed_resume_checks;
}

std::shared_ptr<grpc::Channel> NewChannel(const std::string& target) {
  grpc::ChannelArguments args;
  args.SetMaxReceiveMessageSize(-1);
  args.SetMaxSendMessageSize(-1);
  // Its own subchannel, hence its own TCP connection: a "new channel" is a
  // reconnect as the server sees it.
  args.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
  return grpc::CreateCustomChannel(target, grpc::InsecureChannelCredentials(), args);
}

ClientResult RunSoakClient(int client, const SoakClientOptions& options) {
  ClientResult result;
  SoakClient soak(client, options, &result);
  if (absl::Status status = soak.Run(); !status.ok()) {
    result.failure = absl::StrCat(soak.Where(), ": ", status.message());
  }
  return result;
}

absl::Status ReplaySession(const std::shared_ptr<grpc::Channel>& channel,
                           const SoakClientOptions& options, const SessionRecord& record,
                           int64_t* frames_compared) {
  const std::string where = absl::StrCat("replay of session ", record.session_id, " (client ",
                                         record.client, ", seed ", record.seed, ")");
  std::unique_ptr<v1::FrameDiffuser::Stub> stub = v1::FrameDiffuser::NewStub(channel);
  grpc::ClientContext context;
  std::unique_ptr<Stream> stream = stub->Render(&context);
  auto failed = [&](absl::string_view what) {
    context.TryCancel();
    v1::RenderResponse ignored;
    while (stream->Read(&ignored)) {
    }
    const grpc::Status status = stream->Finish();
    return absl::InternalError(absl::StrCat(where, ": ", what, "; ", Describe(status)));
  };
  v1::RenderResponse response;
  if (!stream->Write(OpenRequest(options, record.seed, 2)) || !stream->Read(&response)) {
    return failed("the open failed");
  }
  if (absl::Status opened = CheckOpened(response, options, record.seed); !opened.ok()) {
    return failed(opened.message());
  }
  const std::vector<RenderedFrame>& frames = record.rendered;
  size_t written = 0;
  for (size_t answered = 0; answered < frames.size();) {
    if (written < frames.size() && written - answered < 2) {
      const RenderedFrame& frame = frames[written];
      if (!stream->Write(MakeFrame(options.size, frame.frame_index, frame.input_seed))) {
        return failed(absl::StrCat("writing frame ", frame.frame_index));
      }
      ++written;
      continue;
    }
    const RenderedFrame& expected = frames[answered];
    if (!stream->Read(&response)) return failed("the stream ended early");
    if (!response.has_frame() || response.frame().frame_index() != expected.frame_index) {
      return failed(
          absl::StrCat("expected frame ", expected.frame_index, ", got ", Describe(response)));
    }
    const uint64_t hash = Fnv1a(response.frame().image().data());
    if (expected.hash.has_value()) {
      if (hash != *expected.hash) {
        return failed(absl::StrCat("frame ", expected.frame_index, " (rendered frame number ",
                                   answered, " of the session) differs: hash ", *expected.hash,
                                   " under load, ", hash, " alone"));
      }
      ++*frames_compared;
    }
    ++answered;
  }
  stream->WritesDone();
  if (stream->Read(&response)) return failed(absl::StrCat("unexpected ", Describe(response)));
  const grpc::Status status = stream->Finish();
  if (!status.ok()) {
    return absl::InternalError(absl::StrCat(where, ": ended with ", Describe(status)));
  }
  return absl::OkStatus();
}

}  // namespace fd::bench
