// FrameBatcher on the tiny real model (fd_pipeline/model): continuity of
// the autoregressive chain, batch independence in both batching modes,
// step-level joining, export/import, isolation of sessions of different
// seeds and sizes, a 500-frame run, and the queue limit, cancellation,
// failure and drain paths. Synchronisation uses futures, gates and the
// scheduler's callbacks, never sleeps.
#include "session/frame_batcher.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <torch/torch.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <future>
#include <initializer_list>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "absl/synchronization/mutex.h"
#include "model/pipeline/environment.h"
#include "model/pipeline/frame_pipeline.h"
#include "session/clock.h"
#include "session/frame_seed.h"
#include "session/pipeline_input_builder.h"
#include "session/session.h"
#include "session/session_store.h"
#include "session/state_blob.h"
#include "tests/testing/golden.h"
#include "tests/testing/scripted_frame_pipeline.h"

namespace fd::session {
namespace {

using ::testing::HasSubstr;
using Image = std::vector<uint8_t>;

// An image's bytes / floats, for comparisons.
Image Bytes(const ImageBuffer& image) { return {image.bytes().begin(), image.bytes().end()}; }
std::vector<float> Floats(const ImageBuffer& image) {
  return {image.float_elements().begin(), image.float_elements().end()};
}
// uint8 HWC RGB bytes of the session's size as a buffer.
ImageBuffer Buffer(const SessionSettings& s, const Image& bytes) {
  ImageBuffer out(s.width, s.height, 3, PixelType::kUint8);
  std::copy(bytes.begin(), bytes.end(), out.mutable_data());
  return out;
}
// A CPU tensor's pixels as a buffer.
ImageBuffer Buffer(const torch::Tensor& hwc) {
  absl::StatusOr<ImageBuffer> out = BufferFromTensor(hwc);
  EXPECT_TRUE(out.ok()) << out.status();
  return out.ok() ? *out : ImageBuffer();
}

constexpr char kEnv[] = "tiny";

// Frame sizes: the tiny model's golden frames are 64x80; a second size
// checks that sessions of different sizes share a queue.
constexpr uint32_t kWidth = 80;
constexpr uint32_t kHeight = 64;

class TinyModel : public ::testing::Environment {
 public:
  void SetUp() override {
    auto env = model::LoadEnvironment(fd::testing::GoldenPath("fd_pipeline/model"));
    ASSERT_TRUE(env.ok()) << env.status();
    environment = *env;
    pipeline = std::make_shared<ModelFramePipeline>(environment);
    model::FramePipelineOptions invariant;
    invariant.batch_invariant = true;
    invariant_pipeline = std::make_shared<ModelFramePipeline>(environment, invariant);
  }
  void TearDown() override {
    pipeline.reset();
    invariant_pipeline.reset();
    environment.reset();
  }
  static inline std::shared_ptr<const model::Environment> environment;
  static inline std::shared_ptr<const ModelFramePipeline> pipeline;
  // FramePipelineOptions::batch_invariant.
  static inline std::shared_ptr<const ModelFramePipeline> invariant_pipeline;
};
::testing::Environment* const tiny_model = ::testing::AddGlobalTestEnvironment(new TinyModel);

SessionSettings Settings(uint64_t seed, uint32_t width = kWidth, uint32_t height = kHeight,
                         uint32_t steps = 3) {
  SessionSettings s;
  s.environment = kEnv;
  s.width = width;
  s.height = height;
  s.seed = seed;
  s.steps = steps;
  s.scheduler = SchedulerKind::kUniPC;
  s.sky_mode = SkyMode::kPreviousOutput;
  s.output_dtype = OutputDType::kFloat32;  // FrameResult::image_float for comparisons
  return s;
}

torch::Generator Gen(uint64_t seed) { return at::make_generator<at::CPUGeneratorImpl>(seed); }

// A deterministic G-buffer for frame `t` of a scene `scene` (uint8
// basecolor, float [0, 1] normals/depth/roughness/metallic).
FrameGBuffer MakeGBuffer(const SessionSettings& s, uint64_t scene, uint64_t t) {
  const int64_t h = s.height, w = s.width;
  torch::Generator g = Gen(scene * 1000003 + t);
  FrameGBuffer gb;
  gb.basecolor = Buffer(torch::randint(0, 256, {h, w, 3}, g, torch::kUInt8));
  gb.normals = Buffer(torch::rand({h, w, 3}, g));
  gb.depth = Buffer(torch::rand({h, w}, g));
  gb.roughness = Buffer(torch::rand({h, w, 1}, g));
  gb.metallic = Buffer(torch::rand({h, w}, g));
  return gb;
}

Image KeyframeImage(const SessionSettings& s, uint64_t salt) {
  torch::Tensor t = torch::randint(0, 256, {s.height, s.width, 3}, Gen(salt), torch::kUInt8);
  return Image(t.data_ptr<uint8_t>(), t.data_ptr<uint8_t>() + t.numel());
}

std::shared_ptr<Session> KeyframeSession(const std::string& id, const SessionSettings& s,
                                         uint64_t key_salt) {
  auto state = SessionState::StartFromKeyframe(s, Buffer(s, KeyframeImage(s, key_salt)),
                                               Buffer(s, KeyframeImage(s, key_salt + 1)));
  EXPECT_TRUE(state.ok()) << state.status();
  return std::make_shared<Session>(id, "client", *std::move(state), RealClock::Get());
}

std::shared_ptr<Session> GBufferOnlySession(const std::string& id, const SessionSettings& s) {
  return std::make_shared<Session>(id, "client", *SessionState::StartFromGBufferOnly(s),
                                   RealClock::Get());
}

struct Scheduler {
  testing::ScriptedFramePipeline* pipeline;  // owned by `scheduler`
  std::unique_ptr<FrameBatcher> scheduler;
};

// A scheduler over the shared tiny pipeline. A huge max_queue_delay makes
// the worker wait until max_batch_size frames are queued (or drain), so
// batch composition is deterministic.
Scheduler MakeScheduler(BatchingMode mode, int max_batch_size,
                        absl::Duration delay = absl::InfiniteDuration(), int max_queue_size = 64,
                        FrameBatcherObserver* observer = nullptr,
                        std::function<void(int, size_t)> before_step = nullptr,
                        int fail_step_call = -1, int workers = 1, bool batch_invariant = false,
                        bool reuse_previous_latent = false) {
  auto scripted = std::make_unique<testing::ScriptedFramePipeline>(
      batch_invariant ? TinyModel::invariant_pipeline : TinyModel::pipeline);
  scripted->before_step = std::move(before_step);
  scripted->fail_step_call = fail_step_call;
  Scheduler s;
  s.pipeline = scripted.get();
  FrameBatcherOptions options;
  options.environment = kEnv;
  options.mode = mode;
  options.max_batch_size = max_batch_size;
  options.max_queue_delay = delay;
  options.max_queue_size = max_queue_size;
  options.workers = workers;
  options.reuse_previous_latent = reuse_previous_latent;
  s.scheduler = std::make_unique<FrameBatcher>(std::move(scripted), options, observer);
  return s;
}

// One session's planned run: frames 0..frames-1 with G-buffers of `scene`.
struct Plan {
  std::shared_ptr<Session> session;
  uint64_t scene = 0;
  int frames = 1;
  uint64_t first_index = 0;
};

struct RunResult {
  std::vector<std::vector<Image>> images;               // [session][frame]
  std::vector<std::vector<std::vector<float>>> floats;  // [session][frame], HWC
  std::vector<std::vector<FrameTimings>> timings;
};

// Renders every plan through `scheduler`: each session's first frame is
// enqueued here, each next frame from the previous frame's callback (the
// state is committed before it). Blocks until all are done.
RunResult RunPlans(FrameBatcher& scheduler, const std::vector<Plan>& plans) {
  struct Shared {
    absl::Mutex mu;
    int remaining = 0;
    RunResult result;
    std::vector<absl::Status> errors;
  } shared;
  shared.result.images.resize(plans.size());
  shared.result.timings.resize(plans.size());
  shared.result.floats.resize(plans.size());
  for (const Plan& p : plans) shared.remaining += p.frames;

  std::function<absl::Status(size_t, int)> enqueue = [&](size_t i, int f) {
    const Plan& p = plans[i];
    FrameJob job;
    job.session = p.session;
    job.frame_index = p.first_index + f;
    job.gbuffer = MakeGBuffer(p.session->settings(), p.scene, p.first_index + f);
    job.done = [&, i, f](absl::StatusOr<FrameResult> r) {
      absl::Status next = absl::OkStatus();
      if (r.ok() && f + 1 < plans[i].frames) next = enqueue(i, f + 1);
      absl::MutexLock lock(&shared.mu);
      if (!r.ok()) shared.errors.push_back(r.status());
      if (!next.ok()) shared.errors.push_back(next);
      if (r.ok()) {
        shared.result.images[i].push_back(Bytes(r->image));
        shared.result.floats[i].push_back(Floats(r->image_float));
        shared.result.timings[i].push_back(r->timings);
      }
      // A failed frame ends its session's run.
      shared.remaining -= (r.ok() && next.ok()) ? 1 : plans[i].frames - f;
    };
    return scheduler.Enqueue(std::move(job));
  };
  for (size_t i = 0; i < plans.size(); ++i) {
    const absl::Status s = enqueue(i, 0);
    EXPECT_TRUE(s.ok()) << s;
    if (!s.ok()) {
      absl::MutexLock lock(&shared.mu);
      shared.remaining -= plans[i].frames;
    }
  }
  absl::MutexLock lock(&shared.mu);
  shared.mu.Await(absl::Condition(
      +[](int* remaining) { return *remaining == 0; }, &shared.remaining));
  for (const absl::Status& e : shared.errors) ADD_FAILURE() << e;
  return std::move(shared.result);
}

// The frames a fresh session renders alone (max batch 1).
RunResult RenderAlone(std::shared_ptr<Session> session, uint64_t scene, int frames) {
  Scheduler s = MakeScheduler(BatchingMode::kWholeFrame, 1, absl::ZeroDuration());
  return RunPlans(*s.scheduler, {{std::move(session), scene, frames}});
}

// Appends the sessions of `more` to `all`.
void Append(RunResult& all, const RunResult& more) {
  all.images.insert(all.images.end(), more.images.begin(), more.images.end());
  all.floats.insert(all.floats.end(), more.floats.begin(), more.floats.end());
  all.timings.insert(all.timings.end(), more.timings.begin(), more.timings.end());
}

// Session `i` of `r` (or one frame result) as a one-session RunResult.
RunResult Only(const RunResult& r, size_t i) {
  return {{r.images[i]}, {r.floats[i]}, {r.timings[i]}};
}
RunResult Only(const FrameResult& f) {
  return {{{Bytes(f.image)}}, {{Floats(f.image_float)}}, {{f.timings}}};
}

// Frames from a promise, for callbacks of single frames.
struct Promised {
  std::promise<absl::StatusOr<FrameResult>> promise;
  std::future<absl::StatusOr<FrameResult>> future = promise.get_future();
  FrameCallback Callback() {
    return [this](absl::StatusOr<FrameResult> r) { promise.set_value(std::move(r)); };
  }
};

FrameJob Job(std::shared_ptr<Session> session, uint64_t index, uint64_t scene, FrameCallback done) {
  FrameJob job;
  job.gbuffer = MakeGBuffer(session->settings(), scene, index);
  job.session = std::move(session);
  job.frame_index = index;
  job.done = std::move(done);
  return job;
}

// Every promised frame was answered CANCELLED, none finished in the pipeline,
// and each session is as before its first frame (nothing committed, nothing
// in flight).
void ExpectCancelledAndUntouched(const Scheduler& sched, std::initializer_list<Promised*> frames,
                                 std::initializer_list<std::shared_ptr<Session>> sessions) {
  for (Promised* frame : frames) {
    EXPECT_EQ(frame->future.get().status().code(), absl::StatusCode::kCancelled);
  }
  EXPECT_EQ(sched.pipeline->finished_items(), 0);
  for (const auto& session : sessions) {
    EXPECT_EQ(session->frame_counter(), 0u);
    EXPECT_FALSE(session->frame_in_flight().has_value());
  }
}

// By default batching changes the order of float sums inside the networks
// (oneDNN and OpenBLAS choose kernels by batch size), so a session's frames
// in a batch equal its frames alone up to float32 noise:
// the float images within 1e-5 (the bound), and the uint8 images
// identical except where the float sits within that noise of a rounding
// boundary (k + 0.5) / 255, by at most 1. Such a rounding flip changes the
// next frame's conditioning (the previous uint8 frame) by 1/255 in one
// value, so the frames after it in that session are held to a looser
// kAfterFlipTol (still far below what a mixed-up session would give).
// FramePipelineOptions::batch_invariant removes the noise and with it the
// flips: BatchInvariantFramesAreBitwiseTheFramesAlone.
::testing::AssertionResult CloseFrames(const RunResult& got, const RunResult& want) {
  constexpr double kFrameTol = 1e-5;
  constexpr double kAfterFlipTol = 1e-3;
  if (got.images.size() != want.images.size()) {
    return ::testing::AssertionFailure() << "session count differs";
  }
  double worst = 0;
  size_t flips = 0;
  for (size_t i = 0; i < got.images.size(); ++i) {
    if (got.images[i].size() != want.images[i].size()) {
      return ::testing::AssertionFailure() << "session " << i << ": frame count differs";
    }
    bool flipped = false;  // a uint8 flip in an earlier frame of this session
    for (size_t f = 0; f < got.images[i].size(); ++f) {
      const double tol = flipped ? kAfterFlipTol : kFrameTol;
      const Image& gu = got.images[i][f];
      const Image& wu = want.images[i][f];
      const std::vector<float>& gf = got.floats[i][f];
      const std::vector<float>& wf = want.floats[i][f];
      if (gu.size() != wu.size() || gf.size() != gu.size() || wf.size() != wu.size()) {
        return ::testing::AssertionFailure() << "session " << i << " frame " << f << ": sizes";
      }
      for (size_t k = 0; k < gu.size(); ++k) {
        const double df = std::abs(double{gf[k]} - double{wf[k]});
        worst = std::max(worst, df);
        if (!(df <= tol)) {
          return ::testing::AssertionFailure() << "session " << i << " frame " << f << " value "
                                               << k << ": float " << gf[k] << " vs " << wf[k];
        }
        const int du = std::abs(int{gu[k]} - int{wu[k]});
        if (du == 0) continue;
        const double x255 = double{wf[k]} * 255;
        const double to_boundary = std::abs(x255 - std::floor(x255) - 0.5);
        if (du > 1 || to_boundary > tol * 255) {
          return ::testing::AssertionFailure()
                 << "session " << i << " frame " << f << " byte " << k << ": " << int{gu[k]}
                 << " vs " << int{wu[k]} << " away from a rounding boundary (float " << wf[k]
                 << ")";
        }
        ++flips;
        flipped = true;
      }
    }
  }
  std::printf("CloseFrames: max float |diff| %.3g, %zu uint8 rounding flips\n", worst, flips);
  return ::testing::AssertionSuccess();
}

torch::Tensor ImageTensor(const SessionSettings& s, const Image& image) {
  return torch::from_blob(const_cast<uint8_t*>(image.data()), {s.height, s.width, 3}, torch::kUInt8)
      .clone();
}

// What the batcher should give the pipeline for frame `t` of a session with
// settings `s`, previous frame `prev` and previous basecolor
// `prev_basecolor` (the session layer's mapping, spelled out).
model::PipelineInput DirectRequest(const SessionSettings& s, uint64_t t, const FrameGBuffer& gb,
                                   const Image& prev, const Image& prev_basecolor) {
  model::PipelineInput r;
  r.previous_frame = ImageTensor(s, prev);
  r.previous_basecolor = ImageTensor(s, prev_basecolor);
  r.basecolor = TensorView(gb.basecolor);
  r.normals = TensorView(gb.normals);
  r.depth = TensorView(gb.depth);
  r.roughness = TensorView(gb.roughness);
  r.metallic = TensorView(gb.metallic);
  r.sky_mode = model::SkyFillMode::kPreviousOutput;
  const uint64_t frame_seed = FrameSeed(s.seed, t);
  r.vae_noise_seed = VaeNoiseSeed(frame_seed);
  r.init_noise_seed = InitNoiseSeed(frame_seed);
  r.steps = static_cast<int>(s.steps);
  r.scheduler = model::SchedulerType::kUniPCMultistep;
  return r;
}

// Frame t's conditioning derives from frame t-1's output exactly as the
// pipeline defines: the batcher's frames equal FramePipeline::Render fed
// with the previous uint8 output and the previous frame's basecolor; a
// keyframe re-seed restarts the chain from the keyframe.
TEST(FrameBatcherTest, ContinuityMatchesDirectPipelineAndReseedRestartsChain) {
  const SessionSettings s = Settings(/*seed=*/7);
  auto session = KeyframeSession("a", s, /*key_salt=*/100);
  Scheduler sched = MakeScheduler(BatchingMode::kStepLevel, 1, absl::ZeroDuration());
  const std::vector<Image> frames = RunPlans(*sched.scheduler, {{session, 1, 3}}).images[0];
  ASSERT_EQ(frames.size(), 3u);

  // Frame 3 re-seeds with a new keyframe (no basecolor: its own basecolor).
  const Image key2 = KeyframeImage(s, 555);
  Promised p3;
  FrameJob job3 = Job(session, 3, 1, p3.Callback());
  job3.reseed = Keyframe{Buffer(s, key2), {}};
  ASSERT_TRUE(sched.scheduler->Enqueue(std::move(job3)).ok());
  absl::StatusOr<FrameResult> r3 = p3.future.get();
  ASSERT_TRUE(r3.ok()) << r3.status();
  EXPECT_EQ(session->frame_counter(), 4u);

  model::FramePipeline direct(TinyModel::environment);
  Image prev = KeyframeImage(s, 100);
  Image prev_basecolor = KeyframeImage(s, 101);
  for (uint64_t t = 0; t < 4; ++t) {
    const FrameGBuffer gb = MakeGBuffer(s, 1, t);
    if (t == 3) {
      prev = key2;
      prev_basecolor = Bytes(gb.basecolor);
    }
    model::PipelineInput r = DirectRequest(s, t, gb, prev, prev_basecolor);
    auto out = direct.Render({r});
    ASSERT_TRUE(out.ok()) << out.status();
    const torch::Tensor img = (*out)[0].image_uint8.contiguous();
    const Image expected(img.data_ptr<uint8_t>(), img.data_ptr<uint8_t>() + img.numel());
    const Image got = t < 3 ? frames[t] : Bytes(r3->image);
    EXPECT_EQ(got, expected) << "frame " << t;
    prev = expected;
    prev_basecolor = Bytes(gb.basecolor);
  }
  // The re-seeded frame differs from continuing the chain.
  EXPECT_NE(Bytes(r3->image), frames[2]);
  // The state holds the last output and this frame's basecolor.
  const SessionState state = session->StateSnapshot();
  EXPECT_EQ(state.previous_frame(), r3->image);
  EXPECT_EQ(Bytes(state.previous_basecolor()), prev_basecolor);
}

// An environment's "previous_latent": "reuse": each committed frame keeps its
// denoised latent, and the next frame takes it instead of the VAE encode of
// the previous output (whose image still gives the irradiance); a keyframe
// (start or re-seed) is encoded as always.
TEST(FrameBatcherTest, ReusedLatentsMatchDirectPipelineAndKeyframesAreEncoded) {
  const SessionSettings s = Settings(/*seed=*/7);
  auto session = KeyframeSession("a", s, /*key_salt=*/100);
  Scheduler sched = MakeScheduler(BatchingMode::kStepLevel, 1, absl::ZeroDuration(), 64, nullptr,
                                  nullptr, -1, 1, false, /*reuse_previous_latent=*/true);
  const std::vector<Image> frames = RunPlans(*sched.scheduler, {{session, 1, 3}}).images[0];
  ASSERT_EQ(frames.size(), 3u);
  const Image key2 = KeyframeImage(s, 555);
  Promised p3;
  FrameJob job3 = Job(session, 3, 1, p3.Callback());
  job3.reseed = Keyframe{Buffer(s, key2), {}};
  ASSERT_TRUE(sched.scheduler->Enqueue(std::move(job3)).ok());
  absl::StatusOr<FrameResult> r3 = p3.future.get();
  ASSERT_TRUE(r3.ok()) << r3.status();

  model::FramePipeline direct(TinyModel::environment);
  Image prev = KeyframeImage(s, 100);
  Image prev_basecolor = KeyframeImage(s, 101);
  torch::Tensor prev_latent;  // undefined: encode (the keyframe)
  std::vector<Image> encoded_chain;
  for (uint64_t t = 0; t < 4; ++t) {
    const FrameGBuffer gb = MakeGBuffer(s, 1, t);
    if (t == 3) {
      prev = key2;
      prev_basecolor = Bytes(gb.basecolor);
      prev_latent = torch::Tensor();
    }
    model::PipelineInput r = DirectRequest(s, t, gb, prev, prev_basecolor);
    r.prev_latent = prev_latent;
    auto out = direct.Render({r});
    ASSERT_TRUE(out.ok()) << out.status();
    const torch::Tensor img = (*out)[0].image_uint8.contiguous();
    const Image expected(img.data_ptr<uint8_t>(), img.data_ptr<uint8_t>() + img.numel());
    const Image got = t < 3 ? frames[t] : Bytes(r3->image);
    EXPECT_EQ(got, expected) << "frame " << t;
    if (t == 1) {  // the same frame with the output encoded instead
      r.prev_latent = torch::Tensor();
      auto encoded = direct.Render({r});
      ASSERT_TRUE(encoded.ok()) << encoded.status();
      EXPECT_FALSE(torch::equal((*encoded)[0].latent, (*out)[0].latent));
    }
    prev = expected;
    prev_basecolor = Bytes(gb.basecolor);
    prev_latent = (*out)[0].latent.clone();
  }
  // The state keeps the last output's latent beside its image.
  const SessionState state = session->StateSnapshot();
  EXPECT_EQ(state.previous_frame(), r3->image);
  ASSERT_FALSE(state.previous_latent().empty());
  EXPECT_TRUE(torch::equal(LatentView(state.previous_latent()), prev_latent));
}

// A kept latent is taken only by the batcher that made it: after a reload
// (another batcher, maybe another autoencoder) or where the environment does
// not reuse latents, the previous frame is encoded instead.
TEST(FrameBatcherTest, ALatentFromAnotherBatcherIsNotTaken) {
  const SessionSettings s = Settings(/*seed=*/7);
  auto make = [] {
    return MakeScheduler(BatchingMode::kStepLevel, 1, absl::ZeroDuration(), 64, nullptr, nullptr,
                         -1, 1, false, /*reuse_previous_latent=*/true);
  };
  Scheduler first = make();
  Scheduler reloaded = make();
  Scheduler encoding = MakeScheduler(BatchingMode::kStepLevel, 1, absl::ZeroDuration());
  // Three twins render frame 0 on `first`, which keeps its latent.
  std::vector<std::shared_ptr<Session>> twins;
  for (const std::string id : {"a", "b", "c"}) {
    twins.push_back(KeyframeSession(id, s, /*key_salt=*/100));
    ASSERT_EQ(RunPlans(*first.scheduler, {{twins.back(), 1, 1, 0}}).images[0].size(), 1u);
    ASSERT_FALSE(twins.back()->StateSnapshot().previous_latent().empty());
  }
  // Frame 1: on another reusing batcher, on one that encodes, on `first`.
  const std::vector<Image> a = RunPlans(*reloaded.scheduler, {{twins[0], 1, 1, 1}}).images[0];
  const std::vector<Image> b = RunPlans(*encoding.scheduler, {{twins[1], 1, 1, 1}}).images[0];
  const std::vector<Image> c = RunPlans(*first.scheduler, {{twins[2], 1, 1, 1}}).images[0];
  ASSERT_EQ(a.size(), 1u);
  ASSERT_EQ(b.size(), 1u);
  ASSERT_EQ(c.size(), 1u);
  EXPECT_EQ(a[0], b[0]);  // both encoded frame 0's output
  EXPECT_NE(a[0], c[0]);  // `first` took its own latent
  // Each state keeps what its last batcher made: a latent, none, a latent.
  EXPECT_FALSE(twins[0]->StateSnapshot().previous_latent().empty());
  EXPECT_TRUE(twins[1]->StateSnapshot().previous_latent().empty());
  EXPECT_NE(twins[0]->StateSnapshot().previous_latent().source,
            twins[2]->StateSnapshot().previous_latent().source);
}

class RecordingObserver : public FrameBatcherObserver {
 public:
  void OnStepBatch(std::string_view, int batch_size) override {
    absl::MutexLock lock(&mu_);
    ++step_batches_[batch_size];
  }
  void OnFrameDone(std::string_view, absl::StatusCode code, const FrameTimings&) override {
    absl::MutexLock lock(&mu_);
    ++done_[code];
  }
  void OnRejected(std::string_view, absl::StatusCode code) override {
    absl::MutexLock lock(&mu_);
    ++rejected_[code];
  }
  std::map<int, int> step_batches() {
    absl::MutexLock lock(&mu_);
    return step_batches_;
  }
  std::map<absl::StatusCode, int> done() {
    absl::MutexLock lock(&mu_);
    return done_;
  }
  std::map<absl::StatusCode, int> rejected() {
    absl::MutexLock lock(&mu_);
    return rejected_;
  }

 private:
  absl::Mutex mu_;
  std::map<int, int> step_batches_;
  std::map<absl::StatusCode, int> done_;
  std::map<absl::StatusCode, int> rejected_;
};

std::vector<Plan> EightSessions(int frames) {
  std::vector<Plan> plans;
  for (int i = 0; i < 8; ++i) {
    plans.push_back({KeyframeSession("s" + std::to_string(i), Settings(100 + i), 200 + 10 * i),
                     static_cast<uint64_t>(i), frames});
  }
  return plans;
}

// A session rendered alone equals the same session rendered while 7 others
// share its batches, in both modes; and both modes give the same frames.
TEST(FrameBatcherTest, SharedBatchesEqualAloneInBothModes) {
  constexpr int kFrames = 2;
  const RunResult alone =
      RenderAlone(KeyframeSession("s0", Settings(100), 200), /*scene=*/0, kFrames);
  std::map<BatchingMode, RunResult> runs;
  for (BatchingMode mode : {BatchingMode::kWholeFrame, BatchingMode::kStepLevel}) {
    RecordingObserver observer;
    Scheduler s = MakeScheduler(mode, 8, absl::InfiniteDuration(), 64, &observer);
    runs[mode] = RunPlans(*s.scheduler, EightSessions(kFrames));
    s.scheduler->Shutdown();
    EXPECT_TRUE(CloseFrames(Only(runs[mode], 0), alone));
    for (const auto& per_session : runs[mode].timings) {
      for (const FrameTimings& t : per_session) {
        EXPECT_EQ(t.batch_size, 8);
        EXPECT_GE(t.total_ms, t.queue_ms);
      }
    }
    // Every step ran the 8 sessions together.
    EXPECT_EQ(observer.step_batches(), (std::map<int, int>{{8, kFrames * 3}}));
    EXPECT_EQ(observer.done(),
              (std::map<absl::StatusCode, int>{{absl::StatusCode::kOk, 8 * kFrames}}));
  }
  EXPECT_TRUE(CloseFrames(runs[BatchingMode::kWholeFrame], runs[BatchingMode::kStepLevel]));
}

// Bitwise equality of two runs (frames as uint8 and as float).
::testing::AssertionResult IdenticalFrames(const RunResult& got, const RunResult& want) {
  if (got.images != want.images) return ::testing::AssertionFailure() << "uint8 frames differ";
  if (got.floats != want.floats) return ::testing::AssertionFailure() << "float frames differ";
  return ::testing::AssertionSuccess();
}

// With FramePipelineOptions::batch_invariant, a session's frames are bitwise
// the frames it renders alone, whatever shares its batches: 8 sessions of 3
// and 5 steps, so that in step-level batching items join and leave batches
// at different steps and no two steps see the same composition; both modes,
// over a chain of frames long enough that a uint8 rounding flip would
// otherwise show (CloseFrames). Also bitwise across the two modes.
TEST(FrameBatcherTest, BatchInvariantFramesAreBitwiseTheFramesAlone) {
  constexpr int kFrames = 3;
  constexpr int kSessions = 8;
  auto settings = [](int i) {
    return Settings(300 + i, kWidth, kHeight, /*steps=*/i % 2 == 0 ? 3 : 5);
  };
  auto plans = [&] {
    std::vector<Plan> out;
    for (int i = 0; i < kSessions; ++i) {
      out.push_back({KeyframeSession("s" + std::to_string(i), settings(i), 400 + 10 * i),
                     static_cast<uint64_t>(i), kFrames});
    }
    return out;
  };
  RunResult alone;
  for (int i = 0; i < kSessions; ++i) {
    Append(alone, RenderAlone(KeyframeSession("s", settings(i), 400 + 10 * i),
                              static_cast<uint64_t>(i), kFrames));
  }
  std::map<BatchingMode, RunResult> runs;
  for (BatchingMode mode : {BatchingMode::kWholeFrame, BatchingMode::kStepLevel}) {
    RecordingObserver observer;
    Scheduler s = MakeScheduler(mode, kSessions, absl::Milliseconds(20), 64, &observer, nullptr, -1,
                                /*workers=*/1, /*batch_invariant=*/true);
    runs[mode] = RunPlans(*s.scheduler, plans());
    s.scheduler->Shutdown();
    EXPECT_TRUE(IdenticalFrames(runs[mode], alone)) << "mode " << static_cast<int>(mode);
    // The frames did share batches.
    int largest = 0;
    for (const auto& [batch_size, calls] : observer.step_batches()) {
      largest = std::max(largest, batch_size);
    }
    EXPECT_GT(largest, 1);
  }
  EXPECT_TRUE(IdenticalFrames(runs[BatchingMode::kWholeFrame], runs[BatchingMode::kStepLevel]));
}

// Two workers split max_batch_size 8: no worker's batch holds more than 4
// frames, every frame is rendered, and the frames equal those of a session
// rendered alone, in both modes. (A finite queue delay: with an infinite
// one, idle workers that each wait for a full batch could wait forever for
// the last frames of the run.)
TEST(FrameBatcherTest, TwoWorkersSplitTheQueueAndEqualAlone) {
  constexpr int kFrames = 2;
  const RunResult alone =
      RenderAlone(KeyframeSession("s0", Settings(100), 200), /*scene=*/0, kFrames);
  for (BatchingMode mode : {BatchingMode::kWholeFrame, BatchingMode::kStepLevel}) {
    RecordingObserver observer;
    Scheduler s = MakeScheduler(mode, 8, absl::Milliseconds(50), 64, &observer, nullptr, -1,
                                /*workers=*/2);
    const RunResult run = RunPlans(*s.scheduler, EightSessions(kFrames));
    s.scheduler->Shutdown();
    EXPECT_TRUE(CloseFrames(Only(run, 0), alone));
    EXPECT_EQ(observer.done(),
              (std::map<absl::StatusCode, int>{{absl::StatusCode::kOk, 8 * kFrames}}));
    int frame_steps = 0;
    for (const auto& [batch_size, calls] : observer.step_batches()) {
      EXPECT_LE(batch_size, 4);
      frame_steps += batch_size * calls;
    }
    EXPECT_EQ(frame_steps, 8 * kFrames * 3);  // 3 steps per frame
  }
}

// Idle workers share the queue: two frames queued together while both
// workers wait run as two batches of one, side by side (not as one batch of
// two on one worker), and equal the frames rendered alone.
TEST(FrameBatcherTest, IdleWorkersShareTheQueue) {
  const SessionSettings sa = Settings(21);
  const SessionSettings sb = Settings(22);
  const RunResult alone_a = RenderAlone(KeyframeSession("a", sa, 30), /*scene=*/1, 1);
  const RunResult alone_b = RenderAlone(KeyframeSession("b", sb, 40), /*scene=*/2, 1);
  for (BatchingMode mode : {BatchingMode::kWholeFrame, BatchingMode::kStepLevel}) {
    RecordingObserver observer;
    // max_batch_size 8 over 2 workers: a worker's batch is full at 4 frames,
    // so the first worker starts at the 1 s queue delay, by when both frames
    // are queued (one batch of 2 before idle workers shared the queue). Had
    // frame b come later, each frame would still run alone.
    Scheduler s = MakeScheduler(mode, 8, absl::Seconds(1), 64, &observer, nullptr, -1,
                                /*workers=*/2);
    ASSERT_TRUE(s.scheduler->AwaitIdleWorkers(2, absl::Seconds(60)));
    Promised pa, pb;
    ASSERT_TRUE(s.scheduler->Enqueue(Job(KeyframeSession("a", sa, 30), 0, 1, pa.Callback())).ok());
    ASSERT_TRUE(s.scheduler->Enqueue(Job(KeyframeSession("b", sb, 40), 0, 2, pb.Callback())).ok());
    absl::StatusOr<FrameResult> a = pa.future.get();
    absl::StatusOr<FrameResult> b = pb.future.get();
    s.scheduler->Shutdown();
    ASSERT_TRUE(a.ok()) << a.status();
    ASSERT_TRUE(b.ok()) << b.status();
    EXPECT_TRUE(CloseFrames(Only(*a), alone_a));
    EXPECT_TRUE(CloseFrames(Only(*b), alone_b));
    // Every step ran a batch of one frame: the two frames were on two workers.
    EXPECT_EQ(observer.step_batches(), (std::map<int, int>{{1, 2 * static_cast<int>(sa.steps)}}))
        << (mode == BatchingMode::kWholeFrame ? "whole-frame" : "step-level");
  }
}

// Cancel finds a frame on any worker.
TEST(FrameBatcherTest, CancelFindsFramesOnEveryWorker) {
  testing::Gate gate;
  std::promise<void> both_stepping;
  std::atomic<int> entered{0};
  Scheduler sched = MakeScheduler(
      BatchingMode::kStepLevel, 1, absl::ZeroDuration(), 64, nullptr,
      [&](int call, size_t) {
        if (call < 2) {
          if (entered.fetch_add(1) == 1) both_stepping.set_value();
          gate.Wait();
        }
      },
      -1, /*workers=*/2);
  auto a = KeyframeSession("w0", Settings(11), 92);
  auto b = KeyframeSession("w1", Settings(12), 93);
  Promised pa, pb;
  ASSERT_TRUE(sched.scheduler->Enqueue(Job(a, 0, 1, pa.Callback())).ok());
  ASSERT_TRUE(sched.scheduler->Enqueue(Job(b, 0, 1, pb.Callback())).ok());
  // Batches of 1: each worker holds one frame in its first step.
  both_stepping.get_future().wait();
  EXPECT_TRUE(sched.scheduler->Cancel("w0"));
  EXPECT_TRUE(sched.scheduler->Cancel("w1"));
  gate.Open();
  ExpectCancelledAndUntouched(sched, {&pa, &pb}, {a, b});
}

// Step-level: a frame that arrives while a batch runs joins it at the next
// step boundary and leaves when its own steps are done; whole-frame: it
// waits for the batch to finish. Frames are the same either way.
TEST(FrameBatcherTest, StepLevelJoinsAtStepBoundary) {
  const SessionSettings sa = Settings(1, kWidth, kHeight, /*steps=*/4);
  const SessionSettings sb = Settings(2, kWidth, kHeight, /*steps=*/2);
  const RunResult alone_a = RenderAlone(KeyframeSession("a", sa, 10), 1, 1);
  const RunResult alone_b = RenderAlone(KeyframeSession("b", sb, 20), 2, 1);

  for (BatchingMode mode : {BatchingMode::kWholeFrame, BatchingMode::kStepLevel}) {
    auto a = KeyframeSession("a", sa, 10);
    auto b = KeyframeSession("b", sb, 20);
    FrameBatcher* scheduler = nullptr;
    Promised pa, pb;
    absl::Mutex order_mu;
    std::vector<std::string> order;
    auto record = [&](Promised& p, const char* name) {
      return [&p, &order_mu, &order, name](absl::StatusOr<FrameResult> r) {
        {
          absl::MutexLock lock(&order_mu);
          order.push_back(name);
        }
        p.promise.set_value(std::move(r));
      };
    };
    // B arrives during A's first step (enqueued from the worker thread).
    Scheduler s = MakeScheduler(mode, 8, absl::ZeroDuration(), 64, nullptr, [&](int call, size_t) {
      if (call == 0) {
        EXPECT_TRUE(scheduler->Enqueue(Job(b, 0, 2, record(pb, "b"))).ok());
      }
    });
    scheduler = s.scheduler.get();
    ASSERT_TRUE(scheduler->Enqueue(Job(a, 0, 1, record(pa, "a"))).ok());
    absl::StatusOr<FrameResult> ra = pa.future.get();
    absl::StatusOr<FrameResult> rb = pb.future.get();
    ASSERT_TRUE(ra.ok()) << ra.status();
    ASSERT_TRUE(rb.ok()) << rb.status();
    EXPECT_TRUE(CloseFrames(Only(*ra), alone_a));
    EXPECT_TRUE(CloseFrames(Only(*rb), alone_b));
    if (mode == BatchingMode::kStepLevel) {
      // B joined after A's step 1 and ran steps 2-3 with A; it finished
      // (2 steps) before A (4 steps).
      EXPECT_EQ(ra->timings.batch_size, 2);
      EXPECT_EQ(rb->timings.batch_size, 2);
      EXPECT_EQ(order, (std::vector<std::string>{"b", "a"}));
      EXPECT_EQ(s.pipeline->step_calls(), 4);
    } else {
      EXPECT_EQ(ra->timings.batch_size, 1);
      EXPECT_EQ(rb->timings.batch_size, 1);
      EXPECT_EQ(order, (std::vector<std::string>{"a", "b"}));
      EXPECT_EQ(s.pipeline->step_calls(), 6);
    }
  }
}

// Export -> import continues with frames identical to an uninterrupted
// session.
TEST(FrameBatcherTest, ExportImportContinuesIdentically) {
  const SessionSettings s = Settings(33);
  // Both runs render one frame at a time, so they match exactly.
  const std::vector<Image> uninterrupted =
      RenderAlone(KeyframeSession("u", s, 300), 3, 4).images[0];
  ASSERT_EQ(uninterrupted.size(), 4u);

  auto first = KeyframeSession("e", s, 300);
  Scheduler sched = MakeScheduler(BatchingMode::kStepLevel, 1, absl::ZeroDuration());
  const std::vector<Image> head = RunPlans(*sched.scheduler, {{first, 3, 2}}).images[0];
  absl::StatusOr<std::string> blob = first->ExportState();
  ASSERT_TRUE(blob.ok()) << blob.status();
  absl::StatusOr<SessionState> imported = ImportState(*blob);
  ASSERT_TRUE(imported.ok()) << imported.status();
  auto resumed = std::make_shared<Session>("e2", "client", *std::move(imported), RealClock::Get());
  const std::vector<Image> tail =
      RunPlans(*sched.scheduler, {{resumed, 3, 2, /*first_index=*/2}}).images[0];
  ASSERT_EQ(head.size(), 2u);
  ASSERT_EQ(tail.size(), 2u);
  EXPECT_EQ(head[0], uninterrupted[0]);
  EXPECT_EQ(head[1], uninterrupted[1]);
  EXPECT_EQ(tail[0], uninterrupted[2]);
  EXPECT_EQ(tail[1], uninterrupted[3]);
}

// Sessions with different seeds, sizes and start modes share one queue (and
// batches) without contaminating each other; a session of another
// environment is refused.
TEST(FrameBatcherTest, DifferentSeedsSizesAndStartsDoNotContaminate) {
  auto make_plans = [] {
    return std::vector<Plan>{
        {KeyframeSession("k1", Settings(1), 400), 4, 2},
        {KeyframeSession("k2", Settings(2, 64, 48), 410), 5, 2},
        {GBufferOnlySession("g3", Settings(3)), 6, 2},
        {KeyframeSession("k4", Settings(4), 400), 4, 2},  // k1 with another seed
    };
  };
  RunResult alone;
  for (Plan& p : make_plans()) Append(alone, RenderAlone(p.session, p.scene, p.frames));
  EXPECT_NE(alone.images[0], alone.images[3]);  // the seed matters

  for (BatchingMode mode : {BatchingMode::kWholeFrame, BatchingMode::kStepLevel}) {
    Scheduler s = MakeScheduler(mode, 4);
    const RunResult shared = RunPlans(*s.scheduler, make_plans());
    EXPECT_TRUE(CloseFrames(shared, alone));
    // One Step call for the 4 (the pipeline runs the 64x48 one in its own
    // network call).
    EXPECT_EQ(shared.timings[0][0].batch_size, 4);
  }

  SessionSettings other = Settings(5);
  other.environment = "elsewhere";
  Scheduler s = MakeScheduler(BatchingMode::kStepLevel, 1);
  const absl::Status status =
      s.scheduler->Enqueue(Job(KeyframeSession("x", other, 1), 0, 1, [](auto) {}));
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(), HasSubstr("elsewhere"));
}

size_t ResidentBytes() {
  FILE* f = std::fopen("/proc/self/statm", "r");
  long pages = 0, resident = 0;
  if (f != nullptr) {
    if (std::fscanf(f, "%ld %ld", &pages, &resident) != 2) resident = 0;
    std::fclose(f);
  }
  return static_cast<size_t>(resident) * static_cast<size_t>(sysconf(_SC_PAGESIZE));
}

// 500 frames of one session: every final latent is finite, outputs are not
// degenerate, and resident memory at frame 500 is within a small slack of
// frame 100 (no per-frame leak).
TEST(FrameBatcherTest, FiveHundredFramesStayFiniteAndMemoryFlat) {
  constexpr int kFrames = 500;
  const SessionSettings s = Settings(77, kWidth, kHeight, /*steps=*/1);
  auto session = GBufferOnlySession("long", s);
  Scheduler sched = MakeScheduler(BatchingMode::kStepLevel, 1, absl::ZeroDuration());
  std::promise<void> finished;
  size_t rss_100 = 0, rss_500 = 0;
  int degenerate = 0;
  absl::Status error;
  std::function<void(uint64_t)> enqueue = [&](uint64_t t) {
    FrameJob job = Job(session, t, 9, [&, t](absl::StatusOr<FrameResult> r) {
      if (!r.ok()) {
        error = r.status();
        finished.set_value();
        return;
      }
      const absl::Span<const uint8_t> pixels = r->image.bytes();
      const auto [lo, hi] = std::minmax_element(pixels.begin(), pixels.end());
      if (*lo == *hi) ++degenerate;
      if (t + 1 == 100) rss_100 = ResidentBytes();
      if (t + 1 == kFrames) {
        rss_500 = ResidentBytes();
        finished.set_value();
        return;
      }
      enqueue(t + 1);
    });
    const absl::Status status = sched.scheduler->Enqueue(std::move(job));
    if (!status.ok()) {
      error = status;
      finished.set_value();
    }
  };
  enqueue(0);
  finished.get_future().wait();
  ASSERT_TRUE(error.ok()) << error;
  EXPECT_EQ(session->frame_counter(), static_cast<uint64_t>(kFrames));
  EXPECT_EQ(sched.pipeline->finished_items(), kFrames);
  EXPECT_EQ(sched.pipeline->non_finite_items(), 0);
  EXPECT_EQ(degenerate, 0);
  constexpr size_t kSlack = 8u << 20;  // allocator noise, not a leak
  EXPECT_LE(rss_500, rss_100 + kSlack)
      << "RSS at frame 100: " << rss_100 << ", at 500: " << rss_500;
  std::printf("RSS at frame 100: %zu B, at frame 500: %zu B\n", rss_100, rss_500);
}

// A bounded queue answers RESOURCE_EXHAUSTED instead of growing; a second
// frame of a session in flight is refused; everything accepted renders.
TEST(FrameBatcherTest, QueueFullIsRefusedAndAcceptedFramesRender) {
  testing::Gate gate;
  std::promise<void> entered;
  RecordingObserver observer;
  Scheduler s = MakeScheduler(BatchingMode::kStepLevel, 1, absl::ZeroDuration(),
                              /*max_queue_size=*/2, &observer, [&](int call, size_t) {
                                if (call == 0) {
                                  entered.set_value();
                                  gate.Wait();
                                }
                              });
  std::vector<std::shared_ptr<Session>> sessions;
  for (int i = 0; i < 4; ++i)
    sessions.push_back(KeyframeSession("q" + std::to_string(i), Settings(i), i));
  Promised p[4];
  ASSERT_TRUE(s.scheduler->Enqueue(Job(sessions[0], 0, 0, p[0].Callback())).ok());
  entered.get_future().wait();  // the worker is inside frame 0's first step
  ASSERT_TRUE(s.scheduler->Enqueue(Job(sessions[1], 0, 1, p[1].Callback())).ok());
  const absl::Status twice = s.scheduler->Enqueue(Job(sessions[1], 1, 1, [](auto) {}));
  EXPECT_EQ(twice.code(), absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(s.scheduler->Enqueue(Job(sessions[2], 0, 2, p[2].Callback())).ok());
  EXPECT_EQ(s.scheduler->queue_depth(), 2);
  const absl::Status full = s.scheduler->Enqueue(Job(sessions[3], 0, 3, p[3].Callback()));
  EXPECT_EQ(full.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(full.message(), HasSubstr("queue full"));
  EXPECT_FALSE(sessions[3]->frame_in_flight().has_value());  // not claimed
  gate.Open();
  for (int i = 0; i < 3; ++i) {
    absl::StatusOr<FrameResult> r = p[i].future.get();
    EXPECT_TRUE(r.ok()) << r.status();
  }
  ASSERT_TRUE(s.scheduler->Enqueue(Job(sessions[3], 0, 3, p[3].Callback())).ok());
  EXPECT_TRUE(p[3].future.get().ok());
  EXPECT_EQ(observer.rejected()[absl::StatusCode::kResourceExhausted], 1);
  EXPECT_EQ(observer.rejected()[absl::StatusCode::kFailedPrecondition], 1);
}

// Cancel drops a queued frame at once and an in-flight one at the next step
// boundary; both get CANCELLED, the sessions' state does not move, and the
// next frame renders as if the cancelled one never happened.
TEST(FrameBatcherTest, CancelDropsQueuedAndInFlightFrames) {
  const SessionSettings s = Settings(9);
  const Image alone = RenderAlone(KeyframeSession("c0", s, 90), 1, 1).images[0][0];
  testing::Gate gate;
  std::promise<void> entered;
  Scheduler sched = MakeScheduler(BatchingMode::kStepLevel, 1, absl::ZeroDuration(), 64, nullptr,
                                  [&](int call, size_t) {
                                    if (call == 0) {
                                      entered.set_value();
                                      gate.Wait();
                                    }
                                  });
  auto in_flight = KeyframeSession("c0", s, 90);
  auto queued = KeyframeSession("c1", Settings(10), 91);
  Promised p0, p1;
  ASSERT_TRUE(sched.scheduler->Enqueue(Job(in_flight, 0, 1, p0.Callback())).ok());
  entered.get_future().wait();
  ASSERT_TRUE(sched.scheduler->Enqueue(Job(queued, 0, 1, p1.Callback())).ok());
  EXPECT_TRUE(sched.scheduler->Cancel("c1"));
  EXPECT_TRUE(sched.scheduler->Cancel("c0"));
  EXPECT_FALSE(sched.scheduler->Cancel("nobody"));
  gate.Open();
  ExpectCancelledAndUntouched(sched, {&p0, &p1}, {in_flight, queued});
  // The same frame index again, with the same noise: as if never cancelled.
  Promised again;
  ASSERT_TRUE(sched.scheduler->Enqueue(Job(in_flight, 0, 1, again.Callback())).ok());
  absl::StatusOr<FrameResult> r = again.future.get();
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(Bytes(r->image), alone);  // both rendered alone: exactly equal
}

// Closing a session through the store cancels its frames the same way: a
// queued one is dropped when the worker reaches it, an in-flight one at the
// next step boundary.
TEST(FrameBatcherTest, ClosingSessionCancelsItsFrames) {
  auto store = SessionStore::Create(SessionStoreOptions{}, RealClock::Get());
  ASSERT_TRUE(store.ok()) << store.status();
  auto running = (*store)->Create("client", *SessionState::StartFromGBufferOnly(Settings(80)));
  auto waiting = (*store)->Create("client", *SessionState::StartFromGBufferOnly(Settings(81)));
  ASSERT_TRUE(running.ok() && waiting.ok());
  testing::Gate gate;
  std::promise<void> entered;
  Scheduler sched = MakeScheduler(BatchingMode::kStepLevel, 1, absl::ZeroDuration(), 64, nullptr,
                                  [&](int call, size_t) {
                                    if (call == 0) {
                                      entered.set_value();
                                      gate.Wait();
                                    }
                                  });
  Promised p0, p1;
  ASSERT_TRUE(sched.scheduler->Enqueue(Job(running->session, 0, 1, p0.Callback())).ok());
  entered.get_future().wait();
  ASSERT_TRUE(sched.scheduler->Enqueue(Job(waiting->session, 0, 2, p1.Callback())).ok());
  ASSERT_TRUE((*store)->Close(running->session->id()).ok());
  ASSERT_TRUE((*store)->Close(waiting->session->id()).ok());
  gate.Open();
  EXPECT_EQ(p0.future.get().status().code(), absl::StatusCode::kCancelled);
  EXPECT_EQ(p1.future.get().status().code(), absl::StatusCode::kCancelled);
  EXPECT_EQ(sched.pipeline->finished_items(), 0);
  EXPECT_EQ(sched.pipeline->step_calls(), 1);  // the running frame stopped after its first step
  EXPECT_EQ(running->session->frame_counter(), 0u);
  EXPECT_FALSE(running->session->frame_in_flight().has_value());
  EXPECT_FALSE(waiting->session->frame_in_flight().has_value());
}

// A failing model call returns its error to every frame in the batch; the
// sessions stay usable with their state unchanged.
TEST(FrameBatcherTest, FailingBatchFailsEveryFrameAndLeavesSessionsUsable) {
  auto make_plans = [] {
    return std::vector<Plan>{{KeyframeSession("f0", Settings(50), 500), 1, 1},
                             {KeyframeSession("f1", Settings(51), 510), 2, 1}};
  };
  RunResult alone;
  for (Plan& p : make_plans()) Append(alone, RenderAlone(p.session, p.scene, 1));

  Scheduler s = MakeScheduler(BatchingMode::kWholeFrame, 2, absl::InfiniteDuration(), 64, nullptr,
                              nullptr, /*fail_step_call=*/1);
  std::vector<Plan> plans = make_plans();
  Promised p[2];
  for (int i = 0; i < 2; ++i) {
    ASSERT_TRUE(
        s.scheduler->Enqueue(Job(plans[i].session, 0, plans[i].scene, p[i].Callback())).ok());
  }
  for (int i = 0; i < 2; ++i) {
    absl::StatusOr<FrameResult> r = p[i].future.get();
    EXPECT_EQ(r.status().code(), absl::StatusCode::kInternal);
    EXPECT_THAT(r.status().message(), HasSubstr("injected failure"));
    EXPECT_EQ(plans[i].session->frame_counter(), 0u);
    EXPECT_FALSE(plans[i].session->frame_in_flight().has_value());
  }
  // Retrying the same frame index renders what an untouched session renders.
  const RunResult retry = RunPlans(*s.scheduler, plans);
  EXPECT_TRUE(CloseFrames(retry, alone));
}

// A frame with invalid inputs fails alone; its batch mate renders.
TEST(FrameBatcherTest, InvalidFrameFailsAlone) {
  Scheduler s = MakeScheduler(BatchingMode::kStepLevel, 2);
  auto good = KeyframeSession("ok", Settings(60), 600);
  auto bad = KeyframeSession("bad", Settings(61), 610);
  Promised pg, pb;
  FrameJob bad_job = Job(bad, 0, 1, pb.Callback());
  // Outside [0, 1]: passes the session's size checks, fails the pipeline's
  // Begin, which is then retried per frame.
  bad_job.gbuffer.normals = Buffer(TensorView(bad_job.gbuffer.normals) + 2);
  ASSERT_TRUE(s.scheduler->Enqueue(Job(good, 0, 1, pg.Callback())).ok());
  ASSERT_TRUE(s.scheduler->Enqueue(std::move(bad_job)).ok());
  absl::StatusOr<FrameResult> rb = pb.future.get();
  EXPECT_EQ(rb.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(rb.status().message(), HasSubstr("normals"));
  EXPECT_TRUE(pg.future.get().ok());
  EXPECT_EQ(good->frame_counter(), 1u);
  EXPECT_EQ(bad->frame_counter(), 0u);
  EXPECT_FALSE(bad->frame_in_flight().has_value());
}

// Shutdown renders what was accepted, then refuses new frames.
TEST(FrameBatcherTest, ShutdownDrainsQueuedFrames) {
  // A batch of 8 that never fills: only the drain starts it.
  Scheduler s = MakeScheduler(BatchingMode::kWholeFrame, 8);
  std::vector<std::shared_ptr<Session>> sessions;
  Promised p[3];
  for (int i = 0; i < 3; ++i) {
    sessions.push_back(KeyframeSession("d" + std::to_string(i), Settings(70 + i), 700 + i));
    ASSERT_TRUE(s.scheduler->Enqueue(Job(sessions[i], 0, i, p[i].Callback())).ok());
  }
  s.scheduler->Shutdown();
  for (int i = 0; i < 3; ++i) {
    absl::StatusOr<FrameResult> r = p[i].future.get();
    ASSERT_TRUE(r.ok()) << r.status();
    EXPECT_EQ(r->timings.batch_size, 3);
    EXPECT_EQ(sessions[i]->frame_counter(), 1u);
  }
  const absl::Status after = s.scheduler->Enqueue(Job(sessions[0], 1, 0, [](auto) {}));
  EXPECT_EQ(after.code(), absl::StatusCode::kUnavailable);
}

}  // namespace
}  // namespace fd::session
