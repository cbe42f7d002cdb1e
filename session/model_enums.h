// The one place where the session's enums (session_settings.h) and the
// model's (model/schedulers/scheduler_settings.h, model/pipeline/conditioning.h) meet.
// The two sides number their values differently (the session's follow the
// wire API), so these are switches, not casts. Thread-safety: pure functions.
#ifndef FD_SESSION_MODEL_ENUMS_H_
#define FD_SESSION_MODEL_ENUMS_H_

#include "model/pipeline/conditioning.h"
#include "model/schedulers/scheduler_settings.h"
#include "session/session_settings.h"

namespace fd::session {

model::SchedulerType ToModelScheduler(SchedulerKind kind);
model::SkyFillMode ToModelSkyMode(SkyMode mode);
SchedulerKind FromModelScheduler(model::SchedulerType type);
SkyMode FromModelSkyMode(model::SkyFillMode mode);

}  // namespace fd::session

#endif  // FD_SESSION_MODEL_ENUMS_H_
