// The environments a server serves: one loaded model::Environment and one
// FrameBatcher (its worker thread and batch queue) per
// environment, with a readiness each.
//
// Model repository: one sub-folder per environment, named after the folder
// (model/pipeline/environment.h describes a folder: the authors' checkpoint layout +
// environment.json). Rescan() compares the folders with what is served:
//   - a new folder is loaded (LOADING, then READY or FAILED);
//   - a vanished folder is removed (UNLOADING: its sessions are evicted,
//     queued frames still rendered, then it is forgotten);
//   - a folder whose files changed (names, sizes, modification times) is
//     reloaded IN THE BACKGROUND: the old model keeps serving, stays READY,
//     and is swapped for the new one once it loaded. The swap is per frame,
//     not per session: a frame already handed to the old model's batcher
//     (queued or rendering) finishes on the old weights (that batcher drains
//     on the loader thread after the swap); every frame handed over after
//     the swap renders on the new weights, new sessions' and OPEN sessions'
//     alike (the server Acquires the environment for every frame). Open
//     sessions carry on across the swap (a session's state is images, not
//     model tensors): their first frame on the new weights is conditioned
//     on the last output of the old ones. A failed reload keeps the old model serving (still READY,
//     readiness_detail empty, as the wire API defines it for READY) and is
//     reported through on_load_finished (the server logs
//     environment_load_failed and counts a failed load in its metrics).
//   - a folder that fails to load (a corrupt or missing file) is FAILED;
//     readiness_detail is the loader's message, which names the file. Other
//     environments and their sessions are not touched.
// Loads run one at a time on the registry's loader thread (loading two
// models at once only competes for the same cores and memory).
//
// Ownership: owns the environments, their batchers and the loader thread.
// Thread-safety: every public method is thread-safe. Callbacks (readiness,
// load results, removals) run with no registry lock held, on the thread that
// caused them (the loader thread for loads).
#ifndef FD_SESSION_ENVIRONMENT_REGISTRY_H_
#define FD_SESSION_ENVIRONMENT_REGISTRY_H_

#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "model/pipeline/environment.h"
#include "session/batcher_observer.h"
#include "session/compute_runtime.h"
#include "session/frame_batcher.h"
#include "session/frame_pipeline_interface.h"
#include "session/session_settings.h"

namespace fd::session {

// Values equal framediffuser.v1.Readiness's.
enum class Readiness : uint8_t {
  kLoading = 1,
  kReady = 2,
  kFailed = 3,
  kUnloading = 4,
};

// "loading", "ready", "failed", "unloading".
std::string_view ReadinessName(Readiness readiness);

// What ListEnvironments and OpenSession need to know about an environment.
// Value type.
struct EnvironmentInfo {
  std::string name;
  std::string dir;  // folder it was loaded from ("" when added in memory)
  std::string description;
  std::string prompt;
  uint32_t native_width = 0;  // 0 until loaded
  uint32_t native_height = 0;
  uint32_t default_steps = 0;
  SchedulerKind default_scheduler = SchedulerKind::kUniPC;
  SkyMode default_sky_mode = SkyMode::kOff;
  // Samplers the checkpoint's batcher config supports.
  std::vector<SchedulerKind> schedulers;
  Readiness readiness = Readiness::kLoading;
  std::string readiness_detail;  // why not READY (empty when READY)
};

// A READY environment, as one frame or session open uses it. Value type; the
// shared pointers keep the model and batcher alive across a concurrent
// reload or removal.
struct EnvironmentHandle {
  EnvironmentInfo info;
  std::shared_ptr<const model::Environment> model;
  std::shared_ptr<FrameBatcher> batcher;
};

// Loads one environment folder with the given options (model::LoadEnvironment).
using EnvironmentLoader = std::function<absl::StatusOr<std::shared_ptr<EnvironmentModel>>(
    const std::string& dir, const EnvironmentLoadOptions& options)>;

// Builds the pipeline a batcher drives (tests wrap the real one).
using PipelineFactory = std::function<std::unique_ptr<FramePipelineInterface>(
    std::shared_ptr<const model::Environment>)>;

struct EnvironmentRegistryOptions {
  model::EnvironmentOptions load;
  // Per-environment batcher settings; `environment` is set per entry.
  FrameBatcherOptions batcher;
  // Borrowed; must outlive the registry. nullptr: no metrics.
  FrameBatcherObserver* batcher_observer = nullptr;
  // nullptr: ModelFramePipeline with `pipeline`.
  PipelineFactory pipeline_factory;
  model::FramePipelineOptions pipeline;
  // On a CPU: time an environment's steps when it loads at 1 intra-op
  // thread, at batcher.threads_per_worker (if > 1), and at 1 with the
  // ControlNet beside the UNet on a companion thread (machines with 2 or more
  // cores; model/pipeline/thread_choice.h, about 15 steps and 8 decodes), and
  // run its pipeline the fastest way, so that more threads never make its
  // frames slower. The companion, and a second thread for the VAE where its
  // decode measured faster so, then run only while a core is free
  // (ControlNetBeside::kWhenCoreFree, FramePipelineOptions::vae_on_free_core:
  // a lone session gets them, a loaded server does not). Ignored with a
  // pipeline_factory or pipeline.intra_op_threads set.
  bool choose_intra_op_threads = false;
  // false: no core beyond the workers' own is used (neither the ControlNet
  // beside the UNet nor the VAE's second thread; not even timed).
  bool allow_controlnet_beside_unet = true;
  // What was chosen for an environment, with the median step times measured
  // (ms; 0 = not timed).
  struct ThreadsChosen {
    int threads = 1;
    bool controlnet_beside_unet = false;
    bool vae_on_free_core = false;
    double step_ms_one = 0;
    double step_ms_many = 0;
    double step_ms_beside = 0;
    double frame_ms_vae_one = 0;
    double frame_ms_vae_two = 0;
  };
  std::function<void(const std::string& name, const ThreadsChosen& chosen)> on_threads_chosen;
  // Loads one folder (nullptr: model::LoadEnvironment). Tests inject a
  // loader that blocks, to observe LOADING.
  EnvironmentLoader loader;
  // An environment's readiness changed; nullopt: it was removed.
  std::function<void(const std::string& name, std::optional<Readiness> readiness)>
      on_readiness_changed;
  // A load (first load or reload) finished.
  std::function<void(const std::string& name, const std::string& dir, const absl::Status& status,
                     double seconds)>
      on_load_finished;
  // An environment is being removed: end its sessions (the server evicts
  // them and tells their streams). Called before its batcher shuts down.
  std::function<void(const std::string& name)> on_removing;
};

class EnvironmentRegistry {
 public:
  explicit EnvironmentRegistry(EnvironmentRegistryOptions options);
  // Shutdown().
  ~EnvironmentRegistry();

  EnvironmentRegistry(const EnvironmentRegistry&) = delete;
  EnvironmentRegistry& operator=(const EnvironmentRegistry&) = delete;

  // Serves an environment loaded by the caller (the embedded default,
  // tests) as READY. ALREADY_EXISTS if the name is taken; INVALID_ARGUMENT
  // for an empty name or a null model; UNAVAILABLE after Shutdown.
  absl::Status AddLoaded(const std::string& name, std::shared_ptr<const model::Environment> model,
                         const std::string& dir = "");

  // Compares the sub-folders of `repository` with what is served (see the
  // file comment) and queues the loads; returns without waiting for them.
  // NOT_FOUND if `repository` is not a readable folder; UNAVAILABLE after
  // Shutdown. Environments added with AddLoaded are left alone.
  absl::Status Rescan(const std::string& repository);

  // Removes an environment: UNLOADING, on_removing, its batcher drains
  // (queued frames are rendered), then it is forgotten. NOT_FOUND if unknown.
  absl::Status Remove(const std::string& name);

  // Blocks until no load is queued or running.
  void AwaitLoads() ABSL_LOCKS_EXCLUDED(mu_);

  // Every environment, sorted by name.
  std::vector<EnvironmentInfo> List() const ABSL_LOCKS_EXCLUDED(mu_);
  // Names of the READY environments.
  std::vector<std::string> ReadyNames() const ABSL_LOCKS_EXCLUDED(mu_);

  // The environment for a new session or frame. NOT_FOUND naming the
  // environment and listing the served ones; UNAVAILABLE "... is loading",
  // "... failed to load: <why>", "... is being removed", or after Shutdown.
  absl::StatusOr<EnvironmentHandle> Acquire(std::string_view name) const ABSL_LOCKS_EXCLUDED(mu_);

  // Stops the loader (a load in progress finishes first), then shuts every
  // batcher down (queued frames are rendered). Idempotent.
  void Shutdown() ABSL_LOCKS_EXCLUDED(mu_);

 private:
  struct Entry {
    EnvironmentInfo info;
    std::string fingerprint;  // of the folder when it was (re)loaded
    bool from_repository = false;
    std::shared_ptr<const model::Environment> model;
    std::shared_ptr<FrameBatcher> batcher;
  };
  struct LoadJob {
    std::string name;
    std::string dir;
    std::string fingerprint;
  };

  void LoaderLoop() ABSL_LOCKS_EXCLUDED(mu_);
  void RunLoad(const LoadJob& job) ABSL_LOCKS_EXCLUDED(mu_);
  std::shared_ptr<FrameBatcher> MakeBatcher(const std::string& name,
                                            std::shared_ptr<const model::Environment> model) const;
  void NotifyReadiness(const std::string& name, std::optional<Readiness> readiness) const;

  const EnvironmentRegistryOptions options_;

  mutable absl::Mutex mu_;
  bool shutdown_ ABSL_GUARDED_BY(mu_) = false;
  std::map<std::string, Entry> entries_ ABSL_GUARDED_BY(mu_);
  std::deque<LoadJob> load_queue_ ABSL_GUARDED_BY(mu_);
  bool loading_ ABSL_GUARDED_BY(mu_) = false;  // a job is running

  absl::Mutex join_mu_;  // serialises Shutdown's join
  std::thread loader_;
};

// The environment's defaults as an EnvironmentInfo (readiness READY).
EnvironmentInfo DescribeEnvironment(const std::string& name, const std::string& dir,
                                    const model::Environment& model);

// Loads an environment held in memory (e.g. compiled into a binary):
// `files` maps paths relative to the environment folder to their bytes,
// which must stay valid during the call (the tensors are copied out).
// Nothing is written to disk. `root` names the folder in the environment's
// `dir` and in messages. Errors as model::LoadEnvironment.
absl::StatusOr<std::shared_ptr<EnvironmentModel>> LoadEnvironmentFromMemory(
    const std::string& root, std::map<std::string, std::string_view> files,
    EnvironmentLoadOptions options);

// A digest of every file under `dir` (relative path, size, modification
// time), to notice that a checkpoint folder changed. "" if unreadable.
std::string FolderFingerprint(const std::string& dir);

}  // namespace fd::session

#endif  // FD_SESSION_ENVIRONMENT_REGISTRY_H_
