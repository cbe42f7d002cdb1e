#include "server/metrics.h"

#include <utility>

#include "absl/status/status.h"
#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "prometheus/counter.h"
#include "prometheus/family.h"
#include "prometheus/gauge.h"
#include "prometheus/histogram.h"
#include "prometheus/metric_family.h"
#include "prometheus/registry.h"
#include "prometheus/text_serializer.h"
#include "session/device_memory.h"
#include "session/end_reason.h"
#include "session/string_view_compat.h"

namespace fd::server {
namespace {

using prometheus::Counter;
using prometheus::Family;
using prometheus::Gauge;
using prometheus::Histogram;
using prometheus::Labels;

// absl::StatusCode values are 0 (OK) .. 16 (UNAUTHENTICATED).
constexpr int kNumStatusCodes = 17;

int CodeIndex(absl::StatusCode code) {
  const int index = static_cast<int>(code);
  return index >= 0 && index < kNumStatusCodes ? index
                                               : static_cast<int>(absl::StatusCode::kUnknown);
}

// The states SetEnvironmentState always reports (0 or 1), so a dashboard
// sees every state series of an environment as soon as it has one.
constexpr std::array<std::string_view, 4> kEnvironmentStates = {"loading", "ready", "failed",
                                                                "unloading"};

enum Stage { kQueue, kEncode, kDenoise, kDecode, kTotal, kNumStages };
constexpr std::array<std::string_view, kNumStages> kStageNames = {"queue", "encode", "denoise",
                                                                  "decode", "total"};

// 1 ms .. 60 s: a queue wait or a tiny model's step is milliseconds, an SD1.5
// frame on CPU is tens of seconds.
const Histogram::BucketBoundaries& StageBuckets() {
  static const auto* const buckets = new Histogram::BucketBoundaries{
      0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 20, 30, 60};
  return *buckets;
}

// 1 .. 64 frames per denoising step (max_batch_size is at most 64).
const Histogram::BucketBoundaries& BatchBuckets() {
  static const auto* const buckets =
      new Histogram::BucketBoundaries{1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64};
  return *buckets;
}

// A model load reads and converts checkpoints: 100 ms (tiny) .. 10 min.
const Histogram::BucketBoundaries& LoadBuckets() {
  static const auto* const buckets =
      new Histogram::BucketBoundaries{0.1, 0.25, 0.5, 1, 2.5, 5, 10, 20, 30, 60, 120, 300, 600};
  return *buckets;
}

template <typename T, typename... Args>
T* GetOrAdd(T*& slot, Family<T>* family, const Labels& labels, Args&&... args) {
  if (slot == nullptr) slot = &family->Add(labels, std::forward<Args>(args)...);
  return slot;
}

template <typename T>
void RemoveChild(T*& slot, Family<T>* family) {
  if (slot != nullptr) family->Remove(slot);
  slot = nullptr;
}

}  // namespace

std::string StatusCodeLabel(absl::StatusCode code) {
  std::string name = absl::StatusCodeToString(static_cast<absl::StatusCode>(CodeIndex(code)));
  absl::AsciiStrToLower(&name);
  return name;
}

// One environment's children; nullptr until first used, so an environment
// only has the series its events produced.
struct ServerMetrics::EnvironmentMetrics {
  std::string name;
  std::array<Counter*, kNumStatusCodes> frames = {};
  std::array<Histogram*, kNumStages> stages = {};
  Histogram* step_batch_size = nullptr;
  Gauge* queue_depth = nullptr;
  Gauge* active_sessions = nullptr;
  Counter* opened = nullptr;
  Counter* resumed = nullptr;
  std::array<Counter*, 5> ended = {};     // by EndReason value (1..4)
  std::array<Counter*, 5> rejected = {};  // by RejectReason value (0..4)
  std::array<Counter*, 2> loads = {};     // [0] error, [1] ok
  Histogram* load_seconds = nullptr;
  absl::flat_hash_map<std::string, Gauge*> states;

  Labels With(std::string key, std::string_view value) const {
    return {{"environment", name}, {std::move(key), std::string(value)}};
  }
  Labels Only() const { return {{"environment", name}}; }
};

ServerMetrics::ServerMetrics(const BuildInfo& build)
    : registry_(std::make_shared<prometheus::Registry>()) {
  prometheus::Registry& r = *registry_;
  families_.frames = &prometheus::BuildCounter()
                          .Name("framediffuser_frames_total")
                          .Help(
                              "Frames that ended, by environment and outcome (ok, cancelled, or "
                              "the lowercase status code name, e.g. invalid_argument)")
                          .Register(r);
  families_.stage_seconds =
      &prometheus::BuildHistogram()
           .Name("framediffuser_frame_stage_seconds")
           .Help(
               "Seconds a successful frame spent per stage: queue (waiting for a batch), "
               "encode, denoise, decode, total (enqueue to result)")
           .Register(r);
  families_.step_batch_size = &prometheus::BuildHistogram()
                                   .Name("framediffuser_step_batch_size")
                                   .Help("Frames denoised together in one denoising step")
                                   .Register(r);
  families_.queue_depth = &prometheus::BuildGauge()
                               .Name("framediffuser_queue_depth")
                               .Help("Frames queued and not yet in a batch, by environment")
                               .Register(r);
  families_.active_sessions = &prometheus::BuildGauge()
                                   .Name("framediffuser_active_sessions")
                                   .Help("Live sessions, by environment")
                                   .Register(r);
  families_.sessions_opened = &prometheus::BuildCounter()
                                   .Name("framediffuser_sessions_opened_total")
                                   .Help("Sessions created, by environment")
                                   .Register(r);
  families_.sessions_resumed = &prometheus::BuildCounter()
                                    .Name("framediffuser_sessions_resumed_total")
                                    .Help("Live sessions resumed by their client, by environment")
                                    .Register(r);
  families_.sessions_ended =
      &prometheus::BuildCounter()
           .Name("framediffuser_sessions_ended_total")
           .Help(
               "Sessions that ended, by environment and reason (closed, expired, evicted, "
               "draining)")
           .Register(r);
  families_.sessions_rejected =
      &prometheus::BuildCounter()
           .Name("framediffuser_sessions_rejected_total")
           .Help(
               "Session creates or resumes refused, by environment (empty when unknown) and "
               "reason")
           .Register(r);
  families_.model_loads = &prometheus::BuildCounter()
                               .Name("framediffuser_model_loads_total")
                               .Help(
                                   "Environment model loads, by environment and outcome (ok, "
                                   "error)")
                               .Register(r);
  families_.model_load_seconds = &prometheus::BuildHistogram()
                                      .Name("framediffuser_model_load_seconds")
                                      .Help(
                                          "Seconds an environment model load took (failed "
                                          "loads included)")
                                      .Register(r);
  families_.environment_state =
      &prometheus::BuildGauge()
           .Name("framediffuser_environment_state")
           .Help(
               "1 for the environment's current state (loading, ready, failed, unloading), 0 "
               "for the others")
           .Register(r);
  families_.streams_open = &prometheus::BuildGauge()
                                .Name("framediffuser_streams_open")
                                .Help("Render streams (RPCs) open now")
                                .Register(r);
  families_.streams_ended = &prometheus::BuildCounter()
                                 .Name("framediffuser_streams_ended_total")
                                 .Help("Render streams ended, by gRPC status code name")
                                 .Register(r);
  families_.device_memory = &prometheus::BuildGauge()
                                 .Name("framediffuser_device_memory_in_use_bytes")
                                 .Help(
                                     "Bytes in use on the model device: resident set size for "
                                     "cpu, the caching allocator's allocated bytes for cuda")
                                 .Register(r);
  families_.build_info = &prometheus::BuildGauge()
                              .Name("framediffuser_build_info")
                              .Help("Always 1; the labels describe the running build")
                              .Register(r);
  families_.build_info
      ->Add({{"version", build.version},
             {"git_commit", build.git_commit},
             {"torch_version", build.torch_version},
             {"device", build.device}})
      .Set(1);
  streams_open_ = &families_.streams_open->Add({});
}

ServerMetrics::~ServerMetrics() {
  // Stop serving before any member the exposer's thread reads goes away.
  absl::MutexLock lock(&exposer_mu_);
  exposer_.reset();
}

absl::StatusOr<int> ServerMetrics::StartExposer(const std::string& address) {
  absl::MutexLock lock(&exposer_mu_);
  if (exposer_ != nullptr) {
    return absl::FailedPreconditionError(
        absl::StrCat("metrics address \"", address,
                     "\": the metrics exposer is already running on port ", exposer_->port()));
  }
  absl::StatusOr<std::unique_ptr<MetricsExposer>> exposer =
      MetricsExposer::Start(address, [this] { return Scrape(); });
  if (!exposer.ok()) return exposer.status();
  exposer_ = *std::move(exposer);
  return exposer_->port();
}

std::string ServerMetrics::Scrape() const {
  SampleScrapeDevice();
  return prometheus::TextSerializer().Serialize(registry_->Collect());
}

std::shared_ptr<prometheus::Registry> ServerMetrics::registry() const { return registry_; }

ServerMetrics::EnvironmentMetrics& ServerMetrics::Env(std::string_view environment) {
  auto it = environments_.find(session::ToAbsl(environment));
  if (it == environments_.end()) {
    auto metrics = std::make_unique<EnvironmentMetrics>();
    metrics->name = std::string(environment);
    it = environments_.emplace(metrics->name, std::move(metrics)).first;
  }
  return *it->second;
}

void ServerMetrics::OnOpened(std::string_view environment) {
  absl::MutexLock lock(&mu_);
  EnvironmentMetrics& env = Env(environment);
  GetOrAdd(env.opened, families_.sessions_opened, env.Only())->Increment();
  GetOrAdd(env.active_sessions, families_.active_sessions, env.Only())->Increment();
}

void ServerMetrics::OnResumed(std::string_view environment) {
  absl::MutexLock lock(&mu_);
  EnvironmentMetrics& env = Env(environment);
  GetOrAdd(env.resumed, families_.sessions_resumed, env.Only())->Increment();
}

void ServerMetrics::OnEnded(std::string_view environment, session::EndReason reason) {
  const size_t index = static_cast<size_t>(reason);
  absl::MutexLock lock(&mu_);
  EnvironmentMetrics& env = Env(environment);
  if (index < env.ended.size()) {
    GetOrAdd(env.ended[index], families_.sessions_ended,
             env.With("reason", session::EndReasonName(reason)))
        ->Increment();
  }
  GetOrAdd(env.active_sessions, families_.active_sessions, env.Only())->Decrement();
}

void ServerMetrics::OnRejected(std::string_view environment, session::RejectReason reason) {
  const size_t index = static_cast<size_t>(reason);
  absl::MutexLock lock(&mu_);
  EnvironmentMetrics& env = Env(environment);
  if (index >= env.rejected.size()) return;
  GetOrAdd(env.rejected[index], families_.sessions_rejected,
           env.With("reason", session::RejectReasonName(reason)))
      ->Increment();
}

void ServerMetrics::OnQueueDepth(std::string_view environment, int depth) {
  absl::MutexLock lock(&mu_);
  EnvironmentMetrics& env = Env(environment);
  GetOrAdd(env.queue_depth, families_.queue_depth, env.Only())->Set(depth);
}

void ServerMetrics::OnStepBatch(std::string_view environment, int batch_size) {
  absl::MutexLock lock(&mu_);
  EnvironmentMetrics& env = Env(environment);
  GetOrAdd(env.step_batch_size, families_.step_batch_size, env.Only(), BatchBuckets())
      ->Observe(batch_size);
}

void ServerMetrics::CountFrame(std::string_view environment, absl::StatusCode code) {
  const int index = CodeIndex(code);
  absl::MutexLock lock(&mu_);
  EnvironmentMetrics& env = Env(environment);
  GetOrAdd(env.frames[index], families_.frames,
           env.With("outcome", StatusCodeLabel(static_cast<absl::StatusCode>(index))))
      ->Increment();
}

void ServerMetrics::OnFrameDone(std::string_view environment, absl::StatusCode code,
                                const session::FrameTimings& timings) {
  CountFrame(environment, code);
  if (code != absl::StatusCode::kOk) return;  // timings are partial
  const std::array<double, kNumStages> ms = {
      timings.queue_ms, timings.encode_ms, timings.denoise_ms, timings.decode_ms, timings.total_ms};
  absl::MutexLock lock(&mu_);
  EnvironmentMetrics& env = Env(environment);
  for (int stage = 0; stage < kNumStages; ++stage) {
    GetOrAdd(env.stages[stage], families_.stage_seconds, env.With("stage", kStageNames[stage]),
             StageBuckets())
        ->Observe(ms[stage] / 1000.0);
  }
}

void ServerMetrics::OnRejected(std::string_view environment, absl::StatusCode code) {
  CountFrame(environment, code);
}

void ServerMetrics::OnFrameRejectedByServer(std::string_view environment, absl::StatusCode code) {
  CountFrame(environment, code);
}

void ServerMetrics::OnModelLoad(std::string_view environment, bool ok, double seconds) {
  absl::MutexLock lock(&mu_);
  EnvironmentMetrics& env = Env(environment);
  GetOrAdd(env.loads[ok ? 1 : 0], families_.model_loads, env.With("outcome", ok ? "ok" : "error"))
      ->Increment();
  GetOrAdd(env.load_seconds, families_.model_load_seconds, env.Only(), LoadBuckets())
      ->Observe(seconds);
}

void ServerMetrics::SetEnvironmentState(std::string_view environment, std::string_view state) {
  absl::MutexLock lock(&mu_);
  EnvironmentMetrics& env = Env(environment);
  const auto child = [&](std::string_view name) -> Gauge* {
    auto it = env.states.find(session::ToAbsl(name));
    if (it == env.states.end()) {
      it = env.states
               .emplace(std::string(name),
                        &families_.environment_state->Add(env.With("state", name)))
               .first;
    }
    return it->second;
  };
  if (env.states.empty()) {
    // A newly known environment: its main series start at 0, so that they
    // exist (and rate() works) before the first event, e.g. for an
    // environment added already loaded, without a model load.
    GetOrAdd(env.frames[CodeIndex(absl::StatusCode::kOk)], families_.frames,
             env.With("outcome", "ok"));
    GetOrAdd(env.opened, families_.sessions_opened, env.Only());
    GetOrAdd(env.active_sessions, families_.active_sessions, env.Only());
    GetOrAdd(env.queue_depth, families_.queue_depth, env.Only());
    GetOrAdd(env.loads[1], families_.model_loads, env.With("outcome", "ok"));
    GetOrAdd(env.loads[0], families_.model_loads, env.With("outcome", "error"));
  }
  for (const std::string_view known : kEnvironmentStates) child(known);
  child(state);
  for (auto& [name, gauge] : env.states) gauge->Set(name == state ? 1 : 0);
}

void ServerMetrics::RemoveEnvironment(std::string_view environment) {
  absl::MutexLock lock(&mu_);
  auto it = environments_.find(session::ToAbsl(environment));
  if (it == environments_.end()) return;
  EnvironmentMetrics& env = *it->second;
  RemoveChild(env.queue_depth, families_.queue_depth);
  RemoveChild(env.active_sessions, families_.active_sessions);
  for (auto& [name, gauge] : env.states) families_.environment_state->Remove(gauge);
  env.states.clear();
}

void ServerMetrics::OnStreamStarted() { streams_open_->Increment(); }

void ServerMetrics::OnStreamEnded(absl::StatusCode code) {
  streams_open_->Decrement();
  const int index = CodeIndex(code);
  absl::MutexLock lock(&mu_);
  GetOrAdd(streams_ended_[index], families_.streams_ended,
           {{"code", StatusCodeLabel(static_cast<absl::StatusCode>(index))}})
      ->Increment();
}

void ServerMetrics::UpdateDeviceMemory(const std::string& device) { SampleDeviceMemory(device); }

void ServerMetrics::SampleDeviceMemory(const std::string& device) const {
  // Sampled outside the lock: reading /proc (or the allocator) may take a
  // moment and must not stall frame hot paths.
  const absl::StatusOr<int64_t> bytes = session::DeviceMemoryInUseBytes(device);
  if (!bytes.ok()) return;
  const std::string& name = device;
  absl::MutexLock lock(&mu_);
  auto it = device_memory_.find(name);
  if (it == device_memory_.end()) {
    it = device_memory_.emplace(name, &families_.device_memory->Add({{"device", name}})).first;
  }
  it->second->Set(static_cast<double>(*bytes));
}

void ServerMetrics::SampleDeviceMemoryAtScrape(const std::string& device) {
  {
    absl::MutexLock lock(&mu_);
    scrape_device_ = device;
  }
  UpdateDeviceMemory(device);
}

void ServerMetrics::SampleScrapeDevice() const {
  std::optional<std::string> device;
  {
    absl::MutexLock lock(&mu_);
    device = scrape_device_;
  }
  if (device.has_value()) SampleDeviceMemory(*device);
}

}  // namespace fd::server
