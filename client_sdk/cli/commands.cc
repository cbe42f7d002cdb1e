#include "client_sdk/cli/commands.h"

#include <unistd.h>

#include <cmath>
#include <condition_variable>
#include <deque>
#include <filesystem>
#include <fstream>
#include <map>
#include <mutex>
#include <optional>
#include <sstream>
#include <thread>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "client_sdk/cli/progress.h"
#include "client_sdk/cli/video.h"
#include "client_sdk/client.h"
#include "client_sdk/dataset.h"
#include "client_sdk/image_io.h"
#include "client_sdk/irradiance.h"
#include "client_sdk/metrics.h"
#include "client_sdk/plot.h"

namespace fd::client::cli {
namespace {

namespace fs = std::filesystem;

int Fail(std::FILE* err, const absl::Status& status) {
  std::fprintf(err, "error: %s\n", std::string(status.message()).c_str());
  return kExitFailure;
}

int Fail(std::FILE* err, const std::string& message) {
  std::fprintf(err, "error: %s\n", message.c_str());
  return kExitFailure;
}

absl::StatusOr<std::unique_ptr<Client>> Connect(const ConnectionArgs& args) {
  ClientOptions options;
  options.target = args.server;
  options.use_tls = args.tls;
  options.bearer_token = args.token;
  if (!args.tls_ca_file.empty()) {
    std::ifstream in(args.tls_ca_file);
    if (!in) return absl::NotFoundError(absl::StrCat("--tls-ca: cannot read ", args.tls_ca_file));
    std::stringstream pem;
    pem << in.rdbuf();
    options.tls_root_certs_pem = pem.str();
  }
  return Client::Create(options);
}

std::string OutputPath(const std::string& dir, int64_t index, const std::string& format) {
  return (fs::path(dir) / "FinalImage" / absl::StrFormat("FinalImage_%04d.%s", index, format))
      .string();
}

// What the writer needs besides the rendered frame, kept from submission.
struct FrameSideInfo {
  Image8 ground_truth;  // empty when the input has none
  Image8 basecolor;
};

// Writes finished frames in order on its own thread (files, video,
// progress), so the session's receiver thread never waits on disk.
class FrameWriter {
 public:
  FrameWriter(const RenderArgs& args, ProgressReporter* progress, VideoWriter* video)
      : args_(args), progress_(progress), video_(video), thread_([this] { Loop(); }) {}
  ~FrameWriter() { (void)Finish(); }

  void AddSideInfo(int64_t index, FrameSideInfo info) {
    std::lock_guard<std::mutex> lock(mu_);
    side_[index] = std::move(info);
  }
  // Seeds the irradiance panel of the first frame.
  void SetPrevious(Image8 output, Image8 basecolor) {
    std::lock_guard<std::mutex> lock(mu_);
    previous_output_ = std::move(output);
    previous_basecolor_ = std::move(basecolor);
  }
  void Push(int64_t index, absl::StatusOr<Frame> frame) {
    std::lock_guard<std::mutex> lock(mu_);
    queue_.emplace_back(index, std::move(frame));
    cv_.notify_all();
  }
  // Drains the queue and stops; returns the first write error, if any.
  absl::Status Finish() {
    {
      std::lock_guard<std::mutex> lock(mu_);
      done_ = true;
      cv_.notify_all();
    }
    if (thread_.joinable()) thread_.join();
    return write_error_;
  }
  int failed_frames() const { return failed_; }
  int written_frames() const { return written_; }

 private:
  void Loop() {
    for (;;) {
      std::pair<int64_t, absl::StatusOr<Frame>> item{0, absl::UnknownError("")};
      {
        std::unique_lock<std::mutex> lock(mu_);
        cv_.wait(lock, [&] { return done_ || !queue_.empty(); });
        if (queue_.empty()) return;
        item = std::move(queue_.front());
        queue_.pop_front();
      }
      Handle(item.first, item.second);
    }
  }

  void Handle(int64_t index, const absl::StatusOr<Frame>& frame) {
    FrameSideInfo info;
    {
      std::lock_guard<std::mutex> lock(mu_);
      auto it = side_.find(index);
      if (it != side_.end()) {
        info = std::move(it->second);
        side_.erase(it);
      }
    }
    if (!frame.ok()) {
      ++failed_;
      progress_->Message(absl::StrCat("frame ", index,
                                      " failed: ", absl::StatusCodeToString(frame.status().code()),
                                      ": ", frame.status().message()));
      return;
    }
    if (!write_error_.ok()) return;
    const std::string path = OutputPath(args_.output, index, args_.format);
    absl::Status written = WriteImage(path, frame->ToImage());
    if (!written.ok()) {
      write_error_ = written;
      progress_->Message(absl::StrCat("cannot write ", path, ": ", written.message()));
      return;
    }
    const Image8 ours = frame->ToImage8();
    if (video_ != nullptr) {
      absl::Status video_status;
      if (args_.side_by_side) {
        Image8 irradiance;
        if (!previous_output_.empty() && !previous_basecolor_.empty()) {
          absl::StatusOr<Image8> map = IrradianceMap(previous_output_, previous_basecolor_);
          if (map.ok()) irradiance = std::move(*map);
        }
        video_status = video_->Write(SideBySide(
            {&info.ground_truth, &ours, &info.basecolor, &irradiance},
            {"GROUND TRUTH", "FRAMEDIFFUSER", "BASECOLOR", "IRRADIANCE"}, ours.width, ours.height));
      } else {
        video_status = video_->Write(ours);
      }
      if (!video_status.ok()) {
        write_error_ = video_status;
        progress_->Message(std::string(video_status.message()));
      }
    }
    previous_output_ = ours;
    previous_basecolor_ = std::move(info.basecolor);
    ++written_;
    progress_->FrameDone(index);
  }

  const RenderArgs& args_;
  ProgressReporter* const progress_;
  VideoWriter* const video_;
  std::mutex mu_;
  std::condition_variable cv_;
  std::deque<std::pair<int64_t, absl::StatusOr<Frame>>> queue_;
  std::map<int64_t, FrameSideInfo> side_;
  bool done_ = false;
  // Writer-thread state.
  Image8 previous_output_;
  Image8 previous_basecolor_;
  absl::Status write_error_;
  int failed_ = 0;
  int written_ = 0;
  std::thread thread_;  // last: starts once the members exist
};

}  // namespace

int RunCommand(const Command& command, std::FILE* out, std::FILE* err) {
  switch (command.kind) {
    case Command::Kind::kHelp:
      std::fputs(UsageText().c_str(), out);
      return kExitOk;
    case Command::Kind::kEnvs:
      return RunEnvs(command, out, err);
    case Command::Kind::kHealth:
      return RunHealth(command, out, err);
    case Command::Kind::kRender:
      return RunRender(command, out, err, ::isatty(::fileno(err)) != 0);
    case Command::Kind::kEval:
      return RunEval(command, out, err);
  }
  return kExitUsage;
}

int RunEnvs(const Command& command, std::FILE* out, std::FILE* err) {
  absl::StatusOr<std::unique_ptr<Client>> client = Connect(command.connection);
  if (!client.ok()) return Fail(err, client.status());
  absl::StatusOr<std::vector<Environment>> environments = (*client)->ListEnvironments();
  if (!environments.ok()) return Fail(err, environments.status());
  if (environments->empty()) {
    std::fprintf(out, "%s serves no environments\n", command.connection.server.c_str());
    return kExitOk;
  }
  std::fprintf(out, "%-24s %-10s %-10s %-6s %-10s %s\n", "NAME", "READINESS", "NATIVE", "STEPS",
               "SAMPLER", "DESCRIPTION");
  for (const Environment& e : *environments) {
    std::string readiness = ReadinessName(e.readiness);
    if (!e.readiness_detail.empty()) absl::StrAppend(&readiness, " (", e.readiness_detail, ")");
    std::fprintf(out, "%-24s %-10s %-10s %-6s %-10s %s\n", e.name.c_str(), readiness.c_str(),
                 absl::StrCat(e.native_width, "x", e.native_height).c_str(),
                 absl::StrCat(e.default_steps, "/", e.max_steps).c_str(),
                 SchedulerName(e.default_scheduler), e.description.c_str());
  }
  return kExitOk;
}

int RunHealth(const Command& command, std::FILE* out, std::FILE* err) {
  absl::StatusOr<std::unique_ptr<Client>> client = Connect(command.connection);
  if (!client.ok()) return Fail(err, client.status());
  absl::StatusOr<HealthStatus> status = (*client)->CheckHealth(command.health.service);
  if (!status.ok()) return Fail(err, status.status());
  std::fprintf(out, "%s%s: %s\n", command.connection.server.c_str(),
               command.health.service.empty() ? "" : (" " + command.health.service).c_str(),
               HealthStatusName(*status));
  return *status == HealthStatus::kServing ? kExitOk : kExitFailure;
}

int RunRender(const Command& command, std::FILE* out, std::FILE* err, bool tty) {
  const RenderArgs& args = command.render;
  // 1. The input, validated up front (names the offending file).
  DatasetOptions dataset_options;
  dataset_options.sequence = args.sequence;
  dataset_options.exr_values = args.exr_values;
  absl::StatusOr<Dataset> dataset = Dataset::Open(args.input, dataset_options);
  if (!dataset.ok()) return Fail(err, absl::StrCat("--input: ", dataset.status().message()));
  std::vector<size_t> positions;
  for (size_t i = 0; i < dataset->frames().size(); ++i) {
    if (args.frames.Contains(dataset->frames()[i].index)) positions.push_back(i);
  }
  if (positions.empty()) {
    return Fail(err, absl::StrCat("--frames: no frame of ", args.input, " (frames ",
                                  dataset->frames().front().index, "..",
                                  dataset->frames().back().index, ") is in the range"));
  }
  const int width = dataset->width(), height = dataset->height();

  // 2. The keyframe.
  Image8 keyframe, keyframe_basecolor;
  if (!args.keyframe_file.empty()) {
    absl::StatusOr<AnyImage> image = ReadImage(args.keyframe_file);
    if (!image.ok()) return Fail(err, absl::StrCat("--keyframe: ", image.status().message()));
    keyframe = ToUint8(ToChannels(*image, 3));
    if (keyframe.width != width || keyframe.height != height) {
      return Fail(err, absl::StrCat("--keyframe: ", args.keyframe_file, " is ", keyframe.width, "x",
                                    keyframe.height, ", the input is ", width, "x", height));
    }
  } else if (args.keyframe_from_input) {
    if (!dataset->has(Buffer::kFinalImage)) {
      return Fail(
          err, absl::StrCat("--keyframe-from-input: ", args.input, " has no FinalImage/ folder"));
    }
    // The ground truth of the frame before the first, else of the first
    // frame itself (what the authors' inference does).
    const int64_t first = dataset->frames()[positions.front()].index;
    const size_t position = dataset->Find(first - 1).value_or(positions.front());
    absl::StatusOr<AnyImage> gt = dataset->ReadBuffer(position, Buffer::kFinalImage);
    absl::StatusOr<AnyImage> bc = dataset->ReadBuffer(position, Buffer::kBaseColor);
    if (!gt.ok()) return Fail(err, gt.status());
    if (!bc.ok()) return Fail(err, bc.status());
    keyframe = ToUint8(*gt);
    keyframe_basecolor = ToUint8(*bc);
  }

  // 3. The server and the environment.
  absl::StatusOr<std::unique_ptr<Client>> client = Connect(command.connection);
  if (!client.ok()) return Fail(err, client.status());
  absl::StatusOr<std::vector<Environment>> environments = (*client)->ListEnvironments();
  if (!environments.ok()) return Fail(err, environments.status());
  const Environment* environment = nullptr;
  std::vector<std::string> names;
  for (const Environment& e : *environments) {
    names.push_back(e.name);
    if (e.name == args.environment) environment = &e;
  }
  if (environment == nullptr) {
    return Fail(err, absl::StrCat("--env: ", command.connection.server, " has no environment '",
                                  args.environment, "' (available: ",
                                  names.empty() ? "none" : absl::StrJoin(names, ", "), ")"));
  }
  if (environment->readiness != Readiness::kReady) {
    return Fail(err, absl::StrCat("--env: environment '", args.environment, "' is ",
                                  ReadinessName(environment->readiness),
                                  environment->readiness_detail.empty()
                                      ? ""
                                      : absl::StrCat(" (", environment->readiness_detail, ")")));
  }

  // 4. Outputs.
  std::string ffmpeg;
  if (!args.video.empty()) {
    ffmpeg = FindExecutable("ffmpeg");
    if (ffmpeg.empty()) {
      return Fail(err, "--video: ffmpeg is not on PATH (Debian: apt-get install ffmpeg)");
    }
  }
  std::error_code ec;
  fs::create_directories(fs::path(args.output) / "FinalImage", ec);
  if (ec)
    return Fail(err, absl::StrCat("--output: cannot create ", args.output, ": ", ec.message()));

  // 5. The session.
  ProgressReporter progress(err, static_cast<int>(positions.size()), tty);
  SessionOptions options;
  options.environment = args.environment;
  options.width = static_cast<uint32_t>(width);
  options.height = static_cast<uint32_t>(height);
  options.seed = args.seed;
  options.steps = args.steps;
  options.scheduler = args.scheduler;
  options.sky_mode = args.sky_mode;
  options.output_dtype = args.format == "exr" ? DType::kFloat16 : DType::kUint8;
  options.max_frames_in_flight = args.max_in_flight;
  options.failover = command.connection.failover;
  if (!keyframe.empty()) options.keyframe = ImageView::Of(keyframe);
  if (!keyframe_basecolor.empty()) options.keyframe_basecolor = ImageView::Of(keyframe_basecolor);
  options.on_failover = [&progress](const FailoverEvent& event) {
    progress.Message(absl::StrCat(
        "failover: the stream broke (", absl::StatusCodeToString(event.cause.code()), ": ",
        event.cause.message(), "); ",
        event.resumed ? "resumed session " : "continuing in new session ", event.new_session_id,
        event.last_frame_index ? absl::StrCat(" after frame ", *event.last_frame_index) : "",
        ", re-sent ", event.resent_frames, " frame(s)"));
  };
  absl::StatusOr<std::unique_ptr<Session>> session = (*client)->OpenSession(options);
  if (!session.ok()) return Fail(err, session.status());
  const SessionSettings settings = (*session)->settings();
  const bool send_sky = settings.sky_mode == SkyMode::kClientImage;
  if (send_sky && !dataset->has(Buffer::kFinalImage)) {
    (void)(*session)->Close();
    return Fail(err,
                absl::StrCat("environment '", args.environment,
                             "' uses sky mode client_image, which needs the input's "
                             "FinalImage/ as the sky; pass --sky-mode previous_output or off"));
  }
  std::fprintf(out,
               "rendering %zu frames of %s (%dx%d) with '%s' on %s: %u steps, %s, seed %llu, "
               "session %s -> %s\n",
               positions.size(), args.input.c_str(), width, height, args.environment.c_str(),
               command.connection.server.c_str(), settings.steps, SchedulerName(settings.scheduler),
               static_cast<unsigned long long>(settings.seed), (*session)->session_id().c_str(),
               args.output.c_str());
  std::fflush(out);

  std::unique_ptr<VideoWriter> video;
  if (!ffmpeg.empty()) {
    absl::StatusOr<std::unique_ptr<VideoWriter>> opened = VideoWriter::Open(
        ffmpeg, args.video, args.side_by_side ? 4 * width : width, height, args.fps);
    if (!opened.ok()) return Fail(err, opened.status());
    video = std::move(*opened);
  }
  FrameWriter writer(args, &progress, video.get());
  if (!keyframe.empty()) {
    // The irradiance the first frame sees, as the server computes it.
    Image8 basecolor = keyframe_basecolor;
    if (basecolor.empty()) {
      absl::StatusOr<AnyImage> first = dataset->ReadBuffer(positions.front(), Buffer::kBaseColor);
      if (first.ok()) basecolor = ToUint8(*first);
    }
    writer.SetPrevious(keyframe, std::move(basecolor));
  }

  // 6. Stream the frames (reading the next while the previous renders).
  absl::Status stopped;
  for (size_t position : positions) {
    absl::StatusOr<DatasetFrame> frame = dataset->ReadFrame(position);
    if (!frame.ok()) {
      stopped = frame.status();
      break;
    }
    FrameRequest request;
    request.frame_index = static_cast<uint64_t>(frame->index);
    request.gbuffer.basecolor = ImageView::Of(frame->basecolor);
    request.gbuffer.normals = ImageView::Of(frame->normals);
    request.gbuffer.depth = ImageView::Of(frame->depth);
    request.gbuffer.roughness = ImageView::Of(frame->roughness);
    if (frame->metallic) request.gbuffer.metallic = ImageView::Of(*frame->metallic);
    if (send_sky && frame->final_image) request.sky = ImageView::Of(*frame->final_image);
    if (video != nullptr && args.side_by_side) {
      FrameSideInfo info;
      if (frame->final_image) info.ground_truth = ToUint8(*frame->final_image);
      info.basecolor = ToUint8(frame->basecolor);
      writer.AddSideInfo(frame->index, std::move(info));
    }
    absl::Status submitted =
        (*session)->Submit(request, [&writer, index = frame->index](absl::StatusOr<Frame> result) {
          writer.Push(index, std::move(result));
        });
    if (!submitted.ok()) {
      stopped = submitted;
      break;
    }
  }
  const absl::Status closed = (*session)->Close();
  const int failovers = (*session)->failover_count();
  session->reset();
  const absl::Status write_status = writer.Finish();
  progress.Finish();
  absl::Status video_status;
  if (video != nullptr) video_status = video->Close();

  const double seconds = progress.elapsed_seconds();
  const int written = writer.written_frames();
  std::fprintf(
      out, "done: %d/%zu frames in %s (%.2f fps), %d failed, %d failover(s); output in %s%s\n",
      written, positions.size(), FormatDuration(seconds).c_str(),
      seconds > 0 ? written / seconds : 0.0, writer.failed_frames(), failovers, args.output.c_str(),
      video != nullptr ? absl::StrCat(", video ", args.video).c_str() : "");
  int status = kExitOk;
  for (const absl::Status& s : {stopped, closed, write_status, video_status}) {
    if (!s.ok()) status = Fail(err, s);
  }
  if (writer.failed_frames() > 0) status = kExitFailure;
  return status;
}

int RunEval(const Command& command, std::FILE* out, std::FILE* err) {
  const EvalArgs& args = command.eval;
  absl::StatusOr<std::map<int64_t, std::string>> pred = ListFrameImages(args.pred);
  if (!pred.ok()) return Fail(err, absl::StrCat("--pred: ", pred.status().message()));
  absl::StatusOr<std::map<int64_t, std::string>> gt = ListFrameImages(args.gt);
  if (!gt.ok()) return Fail(err, absl::StrCat("--gt: ", gt.status().message()));

  std::vector<int64_t> frames;
  std::vector<double> psnr, ssim;
  for (const auto& [index, pred_path] : *pred) {
    if (!args.frames.Contains(index)) continue;
    auto it = gt->find(index);
    if (it == gt->end()) {
      return Fail(
          err, absl::StrCat("mismatched frame numbers: ", pred_path, " has no ground truth frame ",
                            index, " in ", args.gt, " (it has frames ", gt->begin()->first, "..",
                            gt->rbegin()->first, ")"));
    }
    absl::StatusOr<AnyImage> a = ReadImage(pred_path);
    if (!a.ok()) return Fail(err, a.status());
    absl::StatusOr<AnyImage> b = ReadImage(it->second);
    if (!b.ok()) return Fail(err, b.status());
    const ImageF x = ToFloat(ToChannels(*a, 3));
    const ImageF y = ToFloat(ToChannels(*b, 3));
    if (x.width != y.width || x.height != y.height) {
      return Fail(err, absl::StrCat("size mismatch: ", pred_path, " is ", x.width, "x", x.height,
                                    ", ", it->second, " is ", y.width, "x", y.height));
    }
    absl::StatusOr<double> p = Psnr(x, y);
    absl::StatusOr<double> s = Ssim(x, y);
    if (!p.ok()) return Fail(err, p.status());
    if (!s.ok()) return Fail(err, absl::StrCat(pred_path, ": ", s.status().message()));
    frames.push_back(index);
    psnr.push_back(*p);
    ssim.push_back(*s);
    std::fprintf(out, "frame %6lld  PSNR %8.3f dB  SSIM %.4f\n", static_cast<long long>(index), *p,
                 *s);
  }
  if (frames.empty()) return Fail(err, absl::StrCat("no frames of ", args.pred, " in --frames"));
  double psnr_sum = 0, ssim_sum = 0;
  int finite = 0;
  for (size_t i = 0; i < frames.size(); ++i) {
    if (std::isfinite(psnr[i])) {
      psnr_sum += psnr[i];
      ++finite;
    }
    ssim_sum += ssim[i];
  }
  const double psnr_mean = finite > 0 ? psnr_sum / finite : std::numeric_limits<double>::infinity();
  const double ssim_mean = ssim_sum / double(frames.size());
  const int identical = static_cast<int>(frames.size()) - finite;
  std::fprintf(
      out, "mean over %zu frames: PSNR %.3f dB  SSIM %.4f%s\n", frames.size(), psnr_mean, ssim_mean,
      identical > 0 ? absl::StrCat("  (", identical,
                                   " identical frame(s) with infinite PSNR left out of the mean)")
                          .c_str()
                    : "");
  if (!args.csv.empty()) {
    std::ofstream csv(args.csv);
    if (!csv) return Fail(err, absl::StrCat("--csv: cannot write ", args.csv));
    csv << "frame,psnr_db,ssim\n";
    for (size_t i = 0; i < frames.size(); ++i) {
      csv << frames[i] << "," << (std::isfinite(psnr[i]) ? absl::StrFormat("%.6f", psnr[i]) : "inf")
          << "," << absl::StrFormat("%.6f", ssim[i]) << "\n";
    }
    csv << "mean," << (std::isfinite(psnr_mean) ? absl::StrFormat("%.6f", psnr_mean) : "inf") << ","
        << absl::StrFormat("%.6f", ssim_mean) << "\n";
    if (!csv) return Fail(err, absl::StrCat("--csv: cannot write ", args.csv));
  }
  if (!args.plot.empty()) {
    absl::StatusOr<Image8> plot = PlotOverFrames(
        frames, {{"PSNR (DB)", psnr, {31, 119, 180}}, {"SSIM", ssim, {214, 39, 40}}});
    if (!plot.ok()) return Fail(err, plot.status());
    if (absl::Status s = WritePng(args.plot, *plot); !s.ok()) {
      return Fail(err, absl::StrCat("--plot: ", s.message()));
    }
  }
  return kExitOk;
}

}  // namespace fd::client::cli
