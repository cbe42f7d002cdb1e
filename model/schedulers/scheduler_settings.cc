#include "model/schedulers/scheduler_settings.h"

#include <cctype>
#include <cmath>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <utility>

#include "absl/status/status.h"
#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/string_view.h"
#include "base/status_macros.h"
#include "model/checkpoint/json_non_finite.h"

namespace fd::model {
namespace {

using Json = nlohmann::json;

absl::Status WrongType(absl::string_view key, absl::string_view expected, const Json& value) {
  return absl::InvalidArgumentError(
      absl::StrCat("scheduler config: '", key, "' must be ", expected, ", got ", value.dump()));
}

absl::Status ReadDouble(const Json& config, absl::string_view key, double* out) {
  auto it = config.find(std::string(key));
  if (it == config.end() || it->is_null()) return absl::OkStatus();
  if (it->is_number()) {
    *out = it->get<double>();
    return absl::OkStatus();
  }
  if (auto non_finite = NonFiniteFromMarker(*it)) {
    *out = *non_finite;
    return absl::OkStatus();
  }
  return WrongType(key, "a number", *it);
}

absl::Status ReadInt(const Json& config, absl::string_view key, int* out) {
  auto it = config.find(std::string(key));
  if (it == config.end() || it->is_null()) return absl::OkStatus();
  if (!it->is_number_integer()) return WrongType(key, "an integer", *it);
  *out = it->get<int>();
  return absl::OkStatus();
}

absl::Status ReadBool(const Json& config, absl::string_view key, bool* out) {
  auto it = config.find(std::string(key));
  if (it == config.end() || it->is_null()) return absl::OkStatus();
  if (!it->is_boolean()) return WrongType(key, "true or false", *it);
  *out = it->get<bool>();
  return absl::OkStatus();
}

// null keeps the default: diffusers writes e.g. "variance_type": null.
absl::Status ReadString(const Json& config, absl::string_view key, std::string* out) {
  auto it = config.find(std::string(key));
  if (it == config.end() || it->is_null()) return absl::OkStatus();
  if (!it->is_string()) return WrongType(key, "a string", *it);
  *out = it->get<std::string>();
  return absl::OkStatus();
}

absl::StatusOr<TimestepSpacing> ParseSpacing(const std::string& name) {
  if (name == "linspace") return TimestepSpacing::kLinspace;
  if (name == "leading") return TimestepSpacing::kLeading;
  if (name == "trailing") return TimestepSpacing::kTrailing;
  return absl::InvalidArgumentError(absl::StrCat("scheduler config: timestep_spacing '", name,
                                                 "' is not one of linspace, leading, trailing"));
}

absl::Status ReadScalars(const Json& config, SchedulerSettings* s) {
  FD_RETURN_IF_ERROR(ReadInt(config, "num_train_timesteps", &s->num_train_timesteps));
  FD_RETURN_IF_ERROR(ReadDouble(config, "beta_start", &s->beta_start));
  FD_RETURN_IF_ERROR(ReadDouble(config, "beta_end", &s->beta_end));
  FD_RETURN_IF_ERROR(ReadString(config, "beta_schedule", &s->beta_schedule));
  FD_RETURN_IF_ERROR(ReadBool(config, "rescale_betas_zero_snr", &s->rescale_betas_zero_snr));
  FD_RETURN_IF_ERROR(ReadString(config, "prediction_type", &s->prediction_type));
  FD_RETURN_IF_ERROR(ReadInt(config, "steps_offset", &s->steps_offset));
  FD_RETURN_IF_ERROR(ReadInt(config, "solver_order", &s->solver_order));
  FD_RETURN_IF_ERROR(ReadString(config, "solver_type", &s->solver_type));
  FD_RETURN_IF_ERROR(ReadBool(config, "lower_order_final", &s->lower_order_final));
  FD_RETURN_IF_ERROR(ReadString(config, "final_sigmas_type", &s->final_sigmas_type));
  FD_RETURN_IF_ERROR(ReadBool(config, "predict_x0", &s->predict_x0));
  FD_RETURN_IF_ERROR(ReadString(config, "algorithm_type", &s->algorithm_type));
  FD_RETURN_IF_ERROR(ReadBool(config, "euler_at_final", &s->euler_at_final));
  FD_RETURN_IF_ERROR(ReadDouble(config, "lambda_min_clipped", &s->lambda_min_clipped));
  FD_RETURN_IF_ERROR(ReadBool(config, "set_alpha_to_one", &s->set_alpha_to_one));
  FD_RETURN_IF_ERROR(ReadBool(config, "clip_sample", &s->clip_sample));
  FD_RETURN_IF_ERROR(ReadDouble(config, "clip_sample_range", &s->clip_sample_range));
  FD_RETURN_IF_ERROR(ReadBool(config, "thresholding", &s->thresholding));
  FD_RETURN_IF_ERROR(ReadBool(config, "use_karras_sigmas", &s->use_karras_sigmas));
  FD_RETURN_IF_ERROR(ReadBool(config, "use_exponential_sigmas", &s->use_exponential_sigmas));
  FD_RETURN_IF_ERROR(ReadBool(config, "use_beta_sigmas", &s->use_beta_sigmas));
  FD_RETURN_IF_ERROR(ReadBool(config, "use_lu_lambdas", &s->use_lu_lambdas));
  FD_RETURN_IF_ERROR(ReadString(config, "variance_type", &s->variance_type));
  FD_RETURN_IF_ERROR(ReadString(config, "interpolation_type", &s->interpolation_type));
  FD_RETURN_IF_ERROR(ReadString(config, "timestep_type", &s->timestep_type));
  return absl::OkStatus();
}

absl::StatusOr<SchedulerSettings> ParseJson(const Json& config, SchedulerType type) {
  if (!config.is_object()) {
    return absl::InvalidArgumentError("scheduler config: the top level must be a JSON object");
  }
  SchedulerSettings s;
  s.type = type;
  if (type == SchedulerType::kDPMSolverMultistep) s.solver_type = "midpoint";
  if (type == SchedulerType::kUniPCMultistep) s.solver_type = "bh2";
  FD_RETURN_IF_ERROR(ReadScalars(config, &s));
  if (auto it = config.find("timestep_spacing"); it != config.end() && !it->is_null()) {
    if (!it->is_string()) return WrongType("timestep_spacing", "a string", *it);
    auto spacing = ParseSpacing(it->get<std::string>());
    if (!spacing.ok()) return spacing.status();
    s.timestep_spacing = *spacing;
  }
  if (auto it = config.find("trained_betas"); it != config.end() && !it->is_null()) {
    if (!it->is_array()) return WrongType("trained_betas", "a list of numbers or null", *it);
    for (const Json& v : *it) {
      if (!v.is_number()) return WrongType("trained_betas", "a list of numbers or null", *it);
      s.trained_betas.push_back(v.get<double>());
    }
  }
  if (auto it = config.find("disable_corrector"); it != config.end() && !it->is_null()) {
    if (!it->is_array()) return WrongType("disable_corrector", "a list of integers", *it);
    for (const Json& v : *it) {
      if (!v.is_number_integer()) return WrongType("disable_corrector", "a list of integers", *it);
      s.disable_corrector.push_back(v.get<int>());
    }
  }
  return s;
}

}  // namespace

std::string_view SchedulerTypeName(SchedulerType type) {
  switch (type) {
    case SchedulerType::kUniPCMultistep:
      return "UniPCMultistepScheduler";
    case SchedulerType::kDPMSolverMultistep:
      return "DPMSolverMultistepScheduler";
    case SchedulerType::kDDIM:
      return "DDIMScheduler";
    case SchedulerType::kEulerDiscrete:
      return "EulerDiscreteScheduler";
  }
  return "unknown";
}

absl::StatusOr<SchedulerType> SchedulerTypeFromName(std::string_view name) {
  const std::string lower = absl::AsciiStrToLower(std::string(name));
  if (lower == "unipcmultistepscheduler" || lower == "unipc") {
    return SchedulerType::kUniPCMultistep;
  }
  if (lower == "dpmsolvermultistepscheduler" || lower == "dpmsolver++" || lower == "dpm++" ||
      lower == "dpmsolver" || lower == "dpm") {
    return SchedulerType::kDPMSolverMultistep;
  }
  if (lower == "ddimscheduler" || lower == "ddim") return SchedulerType::kDDIM;
  if (lower == "eulerdiscretescheduler" || lower == "euler") return SchedulerType::kEulerDiscrete;
  return absl::InvalidArgumentError(
      absl::StrCat("unknown scheduler '", std::string(name),
                   "': expected one of unipc, dpmsolver++, ddim, euler (or the diffusers class "
                   "names UniPCMultistepScheduler, DPMSolverMultistepScheduler, DDIMScheduler, "
                   "EulerDiscreteScheduler)"));
}

TimestepSpacing EffectiveTimestepSpacing(const SchedulerSettings& settings) {
  if (settings.timestep_spacing.has_value()) return *settings.timestep_spacing;
  return settings.type == SchedulerType::kDDIM ? TimestepSpacing::kLeading
                                               : TimestepSpacing::kLinspace;
}

absl::StatusOr<SchedulerSettings> SchedulerSettingsFromJson(std::string_view json_text,
                                                            SchedulerType type) {
  Json config = Json::parse(QuoteNonFiniteJsonTokens(json_text), /*cb=*/nullptr,
                            /*allow_exceptions=*/false);
  if (config.is_discarded()) {
    return absl::InvalidArgumentError("scheduler config: not valid JSON");
  }
  return ParseJson(config, type);
}

absl::StatusOr<SchedulerSettings> SchedulerSettingsFromFile(const std::string& path,
                                                            SchedulerType type) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat("scheduler config not found: ", path));
  std::stringstream buffer;
  buffer << in.rdbuf();
  auto settings = SchedulerSettingsFromJson(buffer.str(), type);
  if (!settings.ok()) {
    return absl::Status(settings.status().code(),
                        absl::StrCat(path, ": ", settings.status().message()));
  }
  return settings;
}

}  // namespace fd::model
