// Construction options of the noise schedulers (model/schedulers/scheduler.h), i.e. the
// fields of a diffusers `scheduler_config.json` that the four supported
// schedulers read, with diffusers v0.31.0's defaults.
//
// A diffusers pipeline builds its sampler with `Sampler.from_config(config)`:
// the sampler class is chosen by the caller, not by the file's `_class_name`
// (FrameDiffuser builds UniPC from SD1.5's PNDM json). Keys the json does not
// set fall back to the SAMPLER's defaults, which is why an SD1.5 json (no
// `timestep_spacing`) gives linspace for UniPC/DPM-Solver/Euler but leading
// for DDIM: `timestep_spacing` is optional here and resolved per type.
#ifndef FD_MODEL_SCHEDULERS_SCHEDULER_SETTINGS_H_
#define FD_MODEL_SCHEDULERS_SCHEDULER_SETTINGS_H_

#include <limits>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"

namespace fd::model {

enum class SchedulerType {
  kUniPCMultistep,      // UniPCMultistepScheduler (FrameDiffuser's inference sampler)
  kDPMSolverMultistep,  // DPMSolverMultistepScheduler (DPM-Solver++ 2M, the paper's)
  kDDIM,                // DDIMScheduler (eta 0)
  kEulerDiscrete,       // EulerDiscreteScheduler (s_churn 0)
};

// The diffusers class name, e.g. "UniPCMultistepScheduler".
std::string_view SchedulerTypeName(SchedulerType type);

// Accepts the diffusers class names and the short names "unipc", "dpmsolver++"
// (also "dpm", "dpmsolver", "dpm++"), "ddim", "euler" (case-insensitive).
// INVALID_ARGUMENT for anything else (the message lists the accepted names).
absl::StatusOr<SchedulerType> SchedulerTypeFromName(std::string_view name);

enum class TimestepSpacing { kLinspace, kLeading, kTrailing };

struct SchedulerSettings {
  SchedulerType type = SchedulerType::kUniPCMultistep;

  // Noise schedule (all types).
  int num_train_timesteps = 1000;
  double beta_start = 0.0001;
  double beta_end = 0.02;
  std::string beta_schedule = "linear";  // linear | scaled_linear | squaredcos_cap_v2
  std::vector<double> trained_betas;     // non-empty overrides beta_schedule
  bool rescale_betas_zero_snr = false;
  std::string prediction_type = "epsilon";  // epsilon | sample | v_prediction
  // nullopt: the type's own default (DDIM: leading; the others: linspace).
  std::optional<TimestepSpacing> timestep_spacing;
  int steps_offset = 0;

  // Multistep solvers (UniPC, DPM-Solver).
  int solver_order = 2;
  // UniPC: bh1 | bh2 (default bh2; diffusers maps midpoint/heun/logrho to bh2).
  // DPM-Solver: midpoint | heun (default midpoint).
  std::string solver_type;
  bool lower_order_final = true;
  std::string final_sigmas_type = "zero";  // zero | sigma_min (also Euler)

  // UniPC.
  bool predict_x0 = true;
  std::vector<int> disable_corrector;  // step indices whose corrector is skipped

  // DPM-Solver.
  std::string algorithm_type = "dpmsolver++";  // dpmsolver++ | dpmsolver
  bool euler_at_final = false;
  double lambda_min_clipped = -std::numeric_limits<double>::infinity();

  // DDIM (eta is always 0).
  bool set_alpha_to_one = true;
  bool clip_sample = true;
  double clip_sample_range = 1.0;

  // Options diffusers has that this port does not implement; Scheduler::Create
  // returns UNIMPLEMENTED when one is set.
  bool thresholding = false;
  bool use_karras_sigmas = false;
  bool use_exponential_sigmas = false;
  bool use_beta_sigmas = false;
  bool use_lu_lambdas = false;
  std::string variance_type;                  // DPM-Solver: only empty/null supported
  std::string interpolation_type = "linear";  // Euler: only linear
  std::string timestep_type = "discrete";     // Euler: only discrete
};

// The spacing `settings` resolve to (its own or the type's default).
TimestepSpacing EffectiveTimestepSpacing(const SchedulerSettings& settings);

// Parses a diffusers scheduler_config.json as `type.from_config(json)` would:
// known keys are read, unknown keys ignored (PNDM/DDPM-only keys such as
// skip_prk_steps), missing keys keep the defaults above. Accepts the
// non-standard tokens `-Infinity`, `Infinity` and `NaN` that Python's json
// module writes (e.g. lambda_min_clipped). Errors: INVALID_ARGUMENT naming the
// key for malformed json or a value of the wrong type.
absl::StatusOr<SchedulerSettings> SchedulerSettingsFromJson(std::string_view json_text,
                                                            SchedulerType type);

// Reads `path` and parses it as above. NOT_FOUND when the file is missing.
absl::StatusOr<SchedulerSettings> SchedulerSettingsFromFile(const std::string& path,
                                                            SchedulerType type);

}  // namespace fd::model

#endif  // FD_MODEL_SCHEDULERS_SCHEDULER_SETTINGS_H_
