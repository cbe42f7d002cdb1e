// Progress, JSONL log and loss curves; see run_log.h.
#include "trainer/run_log.h"

#include <cmath>
#include <cstdio>
#include <ctime>
#include <filesystem>
#include <fstream>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client_sdk/image_io.h"
#include "client_sdk/plot.h"

namespace fd::trainer {
namespace {

std::string Duration(double seconds) {
  if (!std::isfinite(seconds) || seconds < 0) return "?";
  const int64_t s = static_cast<int64_t>(seconds + 0.5);
  if (s >= 3600) return absl::StrFormat("%dh%02dm", s / 3600, (s / 60) % 60);
  if (s >= 60) return absl::StrFormat("%dm%02ds", s / 60, s % 60);
  return absl::StrFormat("%ds", s);
}

int StageIndex(const std::string& name) {
  for (int i = 0; i < kStageCount; ++i) {
    if (name == StageName(static_cast<Stage>(i))) return i;
  }
  return -1;
}

}  // namespace

RunLog::RunLog(std::string dir, bool progress_bar, int64_t log_every)
    : dir_(std::move(dir)),
      progress_bar_(progress_bar),
      log_every_(std::max<int64_t>(1, log_every)) {}

absl::StatusOr<std::unique_ptr<RunLog>> RunLog::Open(const std::string& train_dir,
                                                     bool progress_bar, int64_t log_every) {
  std::error_code ec;
  std::filesystem::create_directories(train_dir, ec);
  if (ec) return absl::InternalError(absl::StrCat("cannot create ", train_dir, ": ", ec.message()));
  std::unique_ptr<RunLog> log(new RunLog(train_dir, progress_bar, log_every));
  std::ifstream in(train_dir + "/log.jsonl");
  for (std::string line; std::getline(in, line);) {
    nlohmann::json j = nlohmann::json::parse(line, nullptr, /*allow_exceptions=*/false);
    if (!j.is_object() || !j.contains("loss_ema") || !j.contains("stage")) continue;
    const int stage = StageIndex(j.value("stage", ""));
    if (stage < 0) continue;
    log->curve_steps_[stage].push_back(j.value("step", int64_t{0}));
    log->curve_loss_[stage].push_back(j.value("loss_ema", 0.0));
  }
  return log;
}

void RunLog::Append(const nlohmann::json& record) {
  std::ofstream out(dir_ + "/log.jsonl", std::ios::app);
  out << record.dump() << "\n";
}

void RunLog::Step(const StepRecord& r) {
  if (r.step <= 1) ema_count_ = 0;
  ema_ = ema_count_ == 0 ? r.loss : 0.98 * ema_ + 0.02 * r.loss;
  rate_ = ema_count_ == 0 || rate_ == 0 ? 1.0 / std::max(1e-9, r.step_seconds)
                                        : 0.9 * rate_ + 0.1 / std::max(1e-9, r.step_seconds);
  ++ema_count_;
  const bool last = r.step == r.total;
  if (r.step % log_every_ == 0 || last) {
    Append({{"stage", StageName(r.stage)},
            {"step", r.step},
            {"steps", r.total},
            {"loss", r.loss},
            {"loss_ema", ema_},
            {"lr", r.lr},
            {"steps_per_s", rate_},
            {"loader_wait_fraction", r.wait_fraction},
            {"time", static_cast<int64_t>(std::time(nullptr))}});
    curve_steps_[static_cast<int>(r.stage)].push_back(r.step);
    curve_loss_[static_cast<int>(r.stage)].push_back(ema_);
  }
  const std::string line = absl::StrFormat("[%s] step %d/%d  loss %.4f  %.2f steps/s  ETA %s",
                                           StageName(r.stage), r.step, r.total, ema_, rate_,
                                           Duration(static_cast<double>(r.total - r.step) / rate_));
  if (progress_bar_) {
    std::fprintf(stderr, "\r%-78s", line.c_str());
    line_open_ = true;
    if (last) {
      std::fprintf(stderr, "\n");
      line_open_ = false;
    }
  } else if (r.step % log_every_ == 0 || last) {
    std::fprintf(stderr, "%s\n", line.c_str());
  }
}

void RunLog::Event(const std::string& what, const nlohmann::json& fields) {
  nlohmann::json record = fields;
  record["event"] = what;
  record["time"] = static_cast<int64_t>(std::time(nullptr));
  Append(record);
  if (line_open_) {
    std::fprintf(stderr, "\n");
    line_open_ = false;
  }
  std::fprintf(stderr, "%s %s\n", what.c_str(), fields.dump().c_str());
}

absl::Status RunLog::WriteLossCurve(Stage stage) const {
  const int s = static_cast<int>(stage);
  if (curve_steps_[s].size() < 2) return absl::OkStatus();
  std::vector<double> log_loss;
  for (double v : curve_loss_[s]) log_loss.push_back(std::log10(std::max(v, 1e-12)));
  absl::StatusOr<fd::client::Image8> plot = fd::client::PlotOverFrames(
      curve_steps_[s],
      {{absl::StrCat(StageName(stage), ": log10 loss (EMA)"), log_loss, {31, 119, 180}}},
      /*width=*/960, /*height=*/540, /*x_title=*/"OPTIMIZER STEP");
  if (!plot.ok()) return plot.status();
  return fd::client::WritePng(absl::StrCat(dir_, "/loss-", StageName(stage), ".png"), *plot);
}

}  // namespace fd::trainer
