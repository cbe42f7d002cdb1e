#include "session/environment_registry.h"

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <functional>
#include <system_error>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "base/bounded_text.h"
#include "model/pipeline/thread_choice.h"
#include "session/model_enums.h"

namespace fd::session {
namespace {

namespace fs = std::filesystem;

// A folder of the repository holds an environment if it has a checkpoint
// or an environment.json (anything else, e.g. a stray "lost+found", is
// ignored rather than reported as a failed environment).
bool LooksLikeEnvironment(const fs::path& dir) {
  std::error_code ec;
  return fs::is_directory(dir / "unet", ec) || fs::is_regular_file(dir / "environment.json", ec);
}

}  // namespace

std::string_view ReadinessName(Readiness readiness) {
  switch (readiness) {
    case Readiness::kLoading:
      return "loading";
    case Readiness::kReady:
      return "ready";
    case Readiness::kFailed:
      return "failed";
    case Readiness::kUnloading:
      return "unloading";
  }
  return "unknown";
}

EnvironmentInfo DescribeEnvironment(const std::string& name, const std::string& dir,
                                    const model::Environment& model) {
  EnvironmentInfo info;
  info.name = name;
  info.dir = dir;
  info.description = model.settings.description;
  info.prompt = model.settings.prompt;
  info.native_width = static_cast<uint32_t>(model.settings.width);
  info.native_height = static_cast<uint32_t>(model.settings.height);
  info.default_steps = static_cast<uint32_t>(model.settings.steps);
  info.default_scheduler = FromModelScheduler(model.settings.scheduler);
  info.default_sky_mode = FromModelSkyMode(model.settings.sky_mode);
  for (const auto& [type, scheduler] : model.schedulers) {
    info.schedulers.push_back(FromModelScheduler(type));
  }
  info.readiness = Readiness::kReady;
  return info;
}

absl::StatusOr<std::shared_ptr<EnvironmentModel>> LoadEnvironmentFromMemory(
    const std::string& root, std::map<std::string, std::string_view> files,
    EnvironmentLoadOptions options) {
  const model::MemoryFiles memory(root, std::move(files));
  options.files = &memory;
  return model::LoadEnvironment(memory.root(), options);
}

std::string FolderFingerprint(const std::string& dir) {
  std::error_code ec;
  std::vector<std::string> lines;
  for (fs::recursive_directory_iterator
           it(dir, fs::directory_options::follow_directory_symlink, ec),
       end;
       !ec && it != end; it.increment(ec)) {
    std::error_code file_ec;
    if (!it->is_regular_file(file_ec)) continue;
    const auto size = it->file_size(file_ec);
    const auto mtime = it->last_write_time(file_ec).time_since_epoch().count();
    if (file_ec) continue;
    lines.push_back(absl::StrCat(fs::relative(it->path(), dir, file_ec).string(), " ", size, " ",
                                 static_cast<int64_t>(mtime)));
  }
  if (ec) return "";
  std::sort(lines.begin(), lines.end());
  // The sorted listing itself, hashed to keep entries small.
  const size_t digest = std::hash<std::string>{}(absl::StrJoin(lines, "\n"));
  return absl::StrCat(lines.size(), ":", digest);
}

EnvironmentRegistry::EnvironmentRegistry(EnvironmentRegistryOptions options)
    : options_(std::move(options)), loader_([this] { LoaderLoop(); }) {}

EnvironmentRegistry::~EnvironmentRegistry() { Shutdown(); }

std::shared_ptr<FrameBatcher> EnvironmentRegistry::MakeBatcher(
    const std::string& name, std::shared_ptr<const model::Environment> model) const {
  model::FramePipelineOptions pipeline_options = options_.pipeline;
  if (!options_.pipeline_factory && options_.choose_intra_op_threads &&
      pipeline_options.intra_op_threads == 0 && model->device.is_cpu()) {
    model::ThreadChoiceOptions choice_options;
    choice_options.companion = options_.allow_controlnet_beside_unet;
    absl::StatusOr<model::ThreadChoice> choice =
        model::ChooseIntraOpThreads(model, options_.batcher.threads_per_worker, choice_options);
    // A failed measurement keeps the workers' own count (the frames then
    // report the model's error themselves).
    if (choice.ok()) {
      pipeline_options.intra_op_threads = choice->threads;
      pipeline_options.controlnet_beside_unet = choice->controlnet_beside_unet
                                                    ? model::ControlNetBeside::kWhenCoreFree
                                                    : model::ControlNetBeside::kNever;
      pipeline_options.vae_on_free_core = choice->vae_on_free_core;
      if (options_.on_threads_chosen) {
        options_.on_threads_chosen(
            name, {choice->threads, choice->controlnet_beside_unet, choice->vae_on_free_core,
                   choice->step_ms_one, choice->step_ms_many, choice->step_ms_beside,
                   choice->frame_ms_vae_one, choice->frame_ms_vae_two});
      }
    }
  }
  std::unique_ptr<FramePipelineInterface> pipeline =
      options_.pipeline_factory ? options_.pipeline_factory(model)
                                : std::make_unique<ModelFramePipeline>(model, pipeline_options);
  FrameBatcherOptions batcher_options = options_.batcher;
  batcher_options.environment = name;
  batcher_options.reuse_previous_latent = model->settings.reuse_previous_latent;
  FrameBatcherObserver* observer = options_.batcher_observer != nullptr
                                       ? options_.batcher_observer
                                       : NoopFrameBatcherObserver::Get();
  return std::make_shared<FrameBatcher>(std::move(pipeline), batcher_options, observer);
}

void EnvironmentRegistry::NotifyReadiness(const std::string& name,
                                          std::optional<Readiness> readiness) const {
  if (options_.on_readiness_changed) options_.on_readiness_changed(name, readiness);
}

absl::Status EnvironmentRegistry::AddLoaded(const std::string& name,
                                            std::shared_ptr<const model::Environment> model,
                                            const std::string& dir) {
  if (name.empty()) return absl::InvalidArgumentError("environment name: must not be empty");
  if (model == nullptr) return absl::InvalidArgumentError("environment model: must not be null");
  {
    absl::MutexLock lock(&mu_);
    if (shutdown_) return absl::UnavailableError("the server is shutting down");
    if (entries_.count(name) > 0) {
      return absl::AlreadyExistsError(absl::StrCat("environment '", name, "' already exists"));
    }
    Entry entry;
    entry.info = DescribeEnvironment(name, dir, *model);
    entry.batcher = MakeBatcher(name, model);
    entry.model = std::move(model);
    entries_.emplace(name, std::move(entry));
  }
  NotifyReadiness(name, Readiness::kReady);
  return absl::OkStatus();
}

absl::Status EnvironmentRegistry::Rescan(const std::string& repository) {
  std::error_code ec;
  if (!fs::is_directory(repository, ec)) {
    return absl::NotFoundError(
        absl::StrCat("model repository '", repository, "' is not a readable folder"));
  }
  // Folder name -> (path, fingerprint), read without the lock (disk I/O).
  std::map<std::string, std::pair<std::string, std::string>> found;
  for (fs::directory_iterator it(repository, ec), end; !ec && it != end; it.increment(ec)) {
    std::error_code entry_ec;
    if (!it->is_directory(entry_ec) || !LooksLikeEnvironment(it->path())) continue;
    const std::string name = it->path().filename().string();
    if (name.empty() || name[0] == '.') continue;
    found[name] = {it->path().string(), FolderFingerprint(it->path().string())};
  }
  if (ec) {
    return absl::NotFoundError(absl::StrCat("model repository '", repository, "': ", ec.message()));
  }

  std::vector<std::string> to_remove;
  std::vector<std::pair<std::string, Readiness>> changed;
  {
    absl::MutexLock lock(&mu_);
    if (shutdown_) return absl::UnavailableError("the server is shutting down");
    for (const auto& [name, entry] : entries_) {
      if (entry.from_repository && found.count(name) == 0 &&
          entry.info.readiness != Readiness::kUnloading) {
        to_remove.push_back(name);
      }
    }
    for (const auto& [name, where] : found) {
      const auto& [dir, fingerprint] = where;
      auto it = entries_.find(name);
      // A named copy for the lambda: C++17 lambdas cannot capture a
      // structured binding (GCC accepts it, clang does not).
      const std::string& env_name = name;
      const bool queued = std::any_of(load_queue_.begin(), load_queue_.end(),
                                      [&](const LoadJob& job) { return job.name == env_name; });
      if (it == entries_.end()) {
        Entry entry;
        entry.info.name = name;
        entry.info.dir = dir;
        entry.info.readiness = Readiness::kLoading;
        entry.info.readiness_detail = "loading";
        entry.from_repository = true;
        entry.fingerprint = fingerprint;
        entries_.emplace(name, std::move(entry));
        load_queue_.push_back({name, dir, fingerprint});
        changed.emplace_back(name, Readiness::kLoading);
      } else if (it->second.from_repository && it->second.fingerprint != fingerprint && !queued &&
                 it->second.info.readiness != Readiness::kUnloading) {
        // Changed on disk: reload in the background (the old model, if any,
        // keeps serving meanwhile). Remember the new fingerprint now so that a
        // second rescan does not queue it again.
        it->second.fingerprint = fingerprint;
        if (it->second.info.readiness == Readiness::kFailed) {
          it->second.info.readiness = Readiness::kLoading;
          it->second.info.readiness_detail = "loading";
          changed.emplace_back(name, Readiness::kLoading);
        }
        load_queue_.push_back({name, dir, fingerprint});
      }
    }
  }
  for (const auto& [name, readiness] : changed) NotifyReadiness(name, readiness);
  for (const std::string& name : to_remove) {
    absl::Status removed = Remove(name);
    (void)removed;  // NOT_FOUND only if removed concurrently: nothing left to do
  }
  return absl::OkStatus();
}

absl::Status EnvironmentRegistry::Remove(const std::string& name) {
  std::shared_ptr<FrameBatcher> batcher;
  {
    absl::MutexLock lock(&mu_);
    auto it = entries_.find(name);
    if (it == entries_.end() || it->second.info.readiness == Readiness::kUnloading) {
      return absl::NotFoundError(absl::StrCat("environment '", name, "' is not served"));
    }
    it->second.info.readiness = Readiness::kUnloading;
    it->second.info.readiness_detail = "being removed";
    load_queue_.erase(std::remove_if(load_queue_.begin(), load_queue_.end(),
                                     [&](const LoadJob& job) { return job.name == name; }),
                      load_queue_.end());
    batcher = it->second.batcher;
  }
  NotifyReadiness(name, Readiness::kUnloading);
  if (options_.on_removing) options_.on_removing(name);
  // Renders what is queued (the evicted sessions' frames are dropped at the
  // next step boundary) and joins the worker.
  if (batcher != nullptr) batcher->Shutdown();
  {
    absl::MutexLock lock(&mu_);
    auto it = entries_.find(name);
    if (it != entries_.end() && it->second.info.readiness == Readiness::kUnloading) {
      entries_.erase(it);
    }
  }
  NotifyReadiness(name, std::nullopt);
  return absl::OkStatus();
}

void EnvironmentRegistry::AwaitLoads() {
  absl::MutexLock lock(&mu_);
  mu_.Await(absl::Condition(
      +[](EnvironmentRegistry* self) ABSL_EXCLUSIVE_LOCKS_REQUIRED(self->mu_) {
        return self->load_queue_.empty() && !self->loading_;
      },
      this));
}

std::vector<EnvironmentInfo> EnvironmentRegistry::List() const {
  absl::MutexLock lock(&mu_);
  std::vector<EnvironmentInfo> infos;
  infos.reserve(entries_.size());
  for (const auto& [name, entry] : entries_) infos.push_back(entry.info);
  return infos;
}

std::vector<std::string> EnvironmentRegistry::ReadyNames() const {
  absl::MutexLock lock(&mu_);
  std::vector<std::string> names;
  for (const auto& [name, entry] : entries_) {
    if (entry.info.readiness == Readiness::kReady) names.push_back(name);
  }
  return names;
}

absl::StatusOr<EnvironmentHandle> EnvironmentRegistry::Acquire(std::string_view name) const {
  absl::MutexLock lock(&mu_);
  if (shutdown_) return absl::UnavailableError("the server is shutting down");
  auto it = entries_.find(std::string(name));
  if (it == entries_.end()) {
    std::vector<std::string> names;
    for (const auto& [served, entry] : entries_) names.push_back(served);
    // `name` comes from the client: quoted bounded.
    return absl::NotFoundError(absl::StrCat("unknown environment '", BoundedText(name),
                                            "' (served: ", absl::StrJoin(names, ", "), ")"));
  }
  const Entry& entry = it->second;
  switch (entry.info.readiness) {
    case Readiness::kReady:
      return EnvironmentHandle{entry.info, entry.model, entry.batcher};
    case Readiness::kLoading:
      return absl::UnavailableError(
          absl::StrCat("environment '", entry.info.name, "' is still loading; retry shortly"));
    case Readiness::kFailed:
      return absl::UnavailableError(absl::StrCat(
          "environment '", entry.info.name, "' failed to load: ", entry.info.readiness_detail));
    case Readiness::kUnloading:
      return absl::UnavailableError(
          absl::StrCat("environment '", entry.info.name, "' is being removed"));
  }
  return absl::InternalError("unreachable readiness");
}

void EnvironmentRegistry::LoaderLoop() {
  while (true) {
    LoadJob job;
    {
      absl::MutexLock lock(&mu_);
      mu_.Await(absl::Condition(
          +[](EnvironmentRegistry* self) ABSL_EXCLUSIVE_LOCKS_REQUIRED(self->mu_) {
            return self->shutdown_ || !self->load_queue_.empty();
          },
          this));
      if (shutdown_) return;
      job = std::move(load_queue_.front());
      load_queue_.pop_front();
      loading_ = true;
    }
    RunLoad(job);
    absl::MutexLock lock(&mu_);
    loading_ = false;
  }
}

void EnvironmentRegistry::RunLoad(const LoadJob& job) {
  const absl::Time start = absl::Now();
  absl::StatusOr<std::shared_ptr<model::Environment>> loaded =
      options_.loader ? options_.loader(job.dir, options_.load)
                      : model::LoadEnvironment(job.dir, options_.load);
  const double seconds = absl::ToDoubleSeconds(absl::Now() - start);
  absl::Status status = loaded.status();

  std::shared_ptr<FrameBatcher> replaced;
  std::optional<Readiness> readiness;
  if (status.ok()) {
    // Build the batcher (starts its worker) outside the lock.
    std::shared_ptr<const model::Environment> model = *std::move(loaded);
    std::shared_ptr<FrameBatcher> batcher = MakeBatcher(job.name, model);
    absl::MutexLock lock(&mu_);
    auto it = entries_.find(job.name);
    if (it == entries_.end() || it->second.info.readiness == Readiness::kUnloading || shutdown_) {
      replaced = std::move(batcher);  // removed meanwhile: discard
    } else {
      Entry& entry = it->second;
      const bool was_ready = entry.info.readiness == Readiness::kReady;
      entry.info = DescribeEnvironment(job.name, job.dir, *model);
      replaced = std::move(entry.batcher);
      entry.batcher = std::move(batcher);
      entry.model = std::move(model);
      if (!was_ready) readiness = Readiness::kReady;
    }
  } else {
    absl::MutexLock lock(&mu_);
    auto it = entries_.find(job.name);
    if (it != entries_.end() && it->second.info.readiness == Readiness::kLoading) {
      it->second.info.readiness = Readiness::kFailed;
      it->second.info.readiness_detail = std::string(status.message());
      readiness = Readiness::kFailed;
    }
    // A failed RELOAD keeps the old model serving (readiness stays READY).
  }
  if (options_.on_load_finished) options_.on_load_finished(job.name, job.dir, status, seconds);
  if (readiness.has_value()) NotifyReadiness(job.name, readiness);
  // The previous model's batcher renders what it still has queued; new
  // frames already go to the new one.
  if (replaced != nullptr) replaced->Shutdown();
}

void EnvironmentRegistry::Shutdown() {
  absl::MutexLock join(&join_mu_);
  std::vector<std::shared_ptr<FrameBatcher>> batchers;
  {
    absl::MutexLock lock(&mu_);
    shutdown_ = true;
    load_queue_.clear();
    for (auto& [name, entry] : entries_) {
      if (entry.batcher != nullptr) batchers.push_back(entry.batcher);
    }
  }
  if (loader_.joinable()) loader_.join();
  for (const auto& batcher : batchers) batcher->Shutdown();
}

}  // namespace fd::session
