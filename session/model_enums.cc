#include "session/model_enums.h"

namespace fd::session {

model::SchedulerType ToModelScheduler(SchedulerKind kind) {
  switch (kind) {
    case SchedulerKind::kUniPC:
      return model::SchedulerType::kUniPCMultistep;
    case SchedulerKind::kDpmSolverPP2M:
      return model::SchedulerType::kDPMSolverMultistep;
    case SchedulerKind::kDDIM:
      return model::SchedulerType::kDDIM;
    case SchedulerKind::kEulerDiscrete:
      return model::SchedulerType::kEulerDiscrete;
  }
  return model::SchedulerType::kUniPCMultistep;
}

model::SkyFillMode ToModelSkyMode(SkyMode mode) {
  switch (mode) {
    case SkyMode::kClientImage:
      return model::SkyFillMode::kSkyImage;
    case SkyMode::kPreviousOutput:
      return model::SkyFillMode::kPreviousOutput;
    case SkyMode::kOff:
      return model::SkyFillMode::kNone;
  }
  return model::SkyFillMode::kNone;
}

SchedulerKind FromModelScheduler(model::SchedulerType type) {
  switch (type) {
    case model::SchedulerType::kUniPCMultistep:
      return SchedulerKind::kUniPC;
    case model::SchedulerType::kDPMSolverMultistep:
      return SchedulerKind::kDpmSolverPP2M;
    case model::SchedulerType::kDDIM:
      return SchedulerKind::kDDIM;
    case model::SchedulerType::kEulerDiscrete:
      return SchedulerKind::kEulerDiscrete;
  }
  return SchedulerKind::kUniPC;
}

SkyMode FromModelSkyMode(model::SkyFillMode mode) {
  switch (mode) {
    case model::SkyFillMode::kSkyImage:
      return SkyMode::kClientImage;
    case model::SkyFillMode::kPreviousOutput:
      return SkyMode::kPreviousOutput;
    case model::SkyFillMode::kNone:
      return SkyMode::kOff;
  }
  return SkyMode::kOff;
}

}  // namespace fd::session
