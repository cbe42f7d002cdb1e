// ServerMetrics: the server's Prometheus metrics (a prometheus-cpp registry),
// served on their own port by MetricsExposer (see metrics_exposer.h for why
// not prometheus::Exposer). It is the session store's and the frame
// schedulers' observer, so session/ never depends on prometheus.
//
// Families (prefix framediffuser_, units in names, HELP on every family):
//   build_info{version,git_commit,torch_version,device}        gauge, always 1
//   frames_total{environment,outcome}                           counter
//   frame_stage_seconds{environment,stage}                      histogram (OK frames)
//     stage: queue, encode, denoise, decode, total
//   step_batch_size{environment}                                histogram
//   queue_depth{environment}                                    gauge
//   active_sessions{environment}                                gauge
//   sessions_opened_total{environment}                          counter
//   sessions_resumed_total{environment}                         counter
//   sessions_ended_total{environment,reason}                    counter
//     reason: closed, expired, evicted, draining
//   sessions_rejected_total{environment,reason}                 counter
//     reason: session::RejectReasonName; environment "" when unknown
//   model_loads_total{environment,outcome}                      counter (ok/error)
//   model_load_seconds{environment}                             histogram
//   environment_state{environment,state}                        gauge, 1 for the current state
//   streams_open                                                gauge
//   streams_ended_total{code}                                   counter
//   device_memory_in_use_bytes{device}                          gauge
// outcome/code values are "ok", "cancelled" or the lowercase canonical status
// code name ("internal", "resource_exhausted", ...).
//
// Cardinality: labels are environments, stages, reasons, codes and devices,
// all small fixed sets. Never a label per session or per client.
#ifndef FD_SERVER_METRICS_H_
#define FD_SERVER_METRICS_H_

#include <array>
#include <memory>
#include <optional>
#include <string>
#include <string_view>

#include "absl/base/thread_annotations.h"
#include "absl/container/flat_hash_map.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "server/metrics_exposer.h"
#include "session/batcher_observer.h"
#include "session/session_metrics.h"

namespace prometheus {
class Counter;
class Gauge;
class Histogram;
class Registry;
template <typename T>
class Family;
}  // namespace prometheus

namespace fd::server {

// What framediffuser_build_info reports.
struct BuildInfo {
  std::string version;
  std::string git_commit;
  std::string torch_version;
  std::string device;  // e.g. "cpu", "cuda:0"
};

// "ok", "cancelled", "invalid_argument", ...: the lowercase canonical name of
// `code` (out-of-range values map to "unknown"), as used in outcome/code labels.
std::string StatusCodeLabel(absl::StatusCode code);

// Ownership: owns its prometheus::Registry and (after StartExposer) the
// exposer, which stops serving when this object is destroyed. The session
// store and schedulers borrow it as their observer: it must outlive them.
// Thread-safety: every method is thread-safe. Per-environment children are
// created once (Family::Add) and cached under one mutex, so hot paths do a
// hash lookup and an atomic update.
class ServerMetrics final : public session::SessionStoreObserver,
                            public session::FrameBatcherObserver {
 public:
  explicit ServerMetrics(const BuildInfo& build);
  ~ServerMetrics() override;

  ServerMetrics(const ServerMetrics&) = delete;
  ServerMetrics& operator=(const ServerMetrics&) = delete;

  // Serves /metrics on `address` ("host:port", "[ipv6]:port" or "port";
  // "127.0.0.1:0" picks a free port) and returns the bound port. Serving has
  // started when it returns. INVALID_ARGUMENT when `address` is malformed or
  // its host does not resolve, UNAVAILABLE when it cannot be bound,
  // FAILED_PRECONDITION when an exposer is already running.
  absl::StatusOr<int> StartExposer(const std::string& address);

  // The text exposition of everything registered (what /metrics serves),
  // device memory sampled first (see SampleDeviceMemoryAtScrape).
  std::string Scrape() const;

  // The registry, for callers that add their own families (Scrape and
  // /metrics include them). Do not hand it to a prometheus::Exposer: that
  // cannot start in a process that links LibTorch (metrics_exposer.h).
  std::shared_ptr<prometheus::Registry> registry() const;

  // SessionStoreObserver.
  void OnOpened(std::string_view environment) override;
  void OnResumed(std::string_view environment) override;
  void OnEnded(std::string_view environment, session::EndReason reason) override;
  void OnRejected(std::string_view environment, session::RejectReason reason) override;

  // FrameBatcherObserver. OnFrameDone counts the frame by outcome and, for
  // OK frames only, observes the stage histograms (timings are partial
  // otherwise); OnRejected counts it with the code's outcome.
  void OnQueueDepth(std::string_view environment, int depth) override;
  void OnStepBatch(std::string_view environment, int batch_size) override;
  void OnFrameDone(std::string_view environment, absl::StatusCode code,
                   const session::FrameTimings& timings) override;
  void OnRejected(std::string_view environment, absl::StatusCode code) override;

  // A frame the server refused before the scheduler (e.g. bad input):
  // frames_total with outcome = the code's name.
  void OnFrameRejectedByServer(std::string_view environment, absl::StatusCode code);

  // A model load finished: model_loads_total{outcome="ok"|"error"} and the
  // load-seconds histogram (failed loads included).
  void OnModelLoad(std::string_view environment, bool ok, double seconds);

  // environment_state: 1 for `state`, 0 for the other states ("loading",
  // "ready", "failed", "unloading", plus any other state set before). The
  // first call for an environment (or the first after RemoveEnvironment)
  // also starts its frames_total{outcome="ok"}, sessions_opened_total,
  // active_sessions, queue_depth and model_loads_total series at 0.
  void SetEnvironmentState(std::string_view environment, std::string_view state);

  // Drops the environment's gauges (queue depth, active sessions, state) so
  // a removed environment does not report stale values; its counters and
  // histograms stay (they are cumulative). Call it once its sessions have
  // ended and its scheduler stopped: later events recreate its series.
  void RemoveEnvironment(std::string_view environment);

  // Render streams (RPCs): streams_open, and streams_ended_total{code}.
  void OnStreamStarted();
  void OnStreamEnded(absl::StatusCode code);

  // Samples session::DeviceMemoryInUseBytes(device) into device_memory_in_use_bytes.
  // A device that cannot be measured (UNIMPLEMENTED) leaves no sample.
  void UpdateDeviceMemory(const std::string& device);

  // Makes every scrape (Scrape() and /metrics) sample `device` first, so the
  // gauge is fresh without a polling thread.
  void SampleDeviceMemoryAtScrape(const std::string& device);

 private:
  struct EnvironmentMetrics;

  // Families, owned by registry_ (stable addresses).
  struct Families {
    prometheus::Family<prometheus::Counter>* frames;
    prometheus::Family<prometheus::Histogram>* stage_seconds;
    prometheus::Family<prometheus::Histogram>* step_batch_size;
    prometheus::Family<prometheus::Gauge>* queue_depth;
    prometheus::Family<prometheus::Gauge>* active_sessions;
    prometheus::Family<prometheus::Counter>* sessions_opened;
    prometheus::Family<prometheus::Counter>* sessions_resumed;
    prometheus::Family<prometheus::Counter>* sessions_ended;
    prometheus::Family<prometheus::Counter>* sessions_rejected;
    prometheus::Family<prometheus::Counter>* model_loads;
    prometheus::Family<prometheus::Histogram>* model_load_seconds;
    prometheus::Family<prometheus::Gauge>* environment_state;
    prometheus::Family<prometheus::Gauge>* streams_open;
    prometheus::Family<prometheus::Counter>* streams_ended;
    prometheus::Family<prometheus::Gauge>* device_memory;
    prometheus::Family<prometheus::Gauge>* build_info;
  };

  // The environment's cached children, created on first use.
  EnvironmentMetrics& Env(std::string_view environment) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void CountFrame(std::string_view environment, absl::StatusCode code);
  void SampleScrapeDevice() const;
  // UpdateDeviceMemory for const Scrape(): only the gauge cache changes.
  void SampleDeviceMemory(const std::string& device) const;

  const std::shared_ptr<prometheus::Registry> registry_;
  Families families_;
  prometheus::Gauge* streams_open_;

  mutable absl::Mutex mu_;
  absl::flat_hash_map<std::string, std::unique_ptr<EnvironmentMetrics>> environments_
      ABSL_GUARDED_BY(mu_);
  // By absl::StatusCode value (0..16).
  std::array<prometheus::Counter*, 17> streams_ended_ ABSL_GUARDED_BY(mu_) = {};
  mutable absl::flat_hash_map<std::string, prometheus::Gauge*> device_memory_ ABSL_GUARDED_BY(mu_);
  std::optional<std::string> scrape_device_ ABSL_GUARDED_BY(mu_);

  // Last: the exposer (its thread calls Scrape) stops first.
  absl::Mutex exposer_mu_;
  std::unique_ptr<MetricsExposer> exposer_ ABSL_GUARDED_BY(exposer_mu_);
};

}  // namespace fd::server

#endif  // FD_SERVER_METRICS_H_
