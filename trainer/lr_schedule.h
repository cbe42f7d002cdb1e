// diffusers.optimization.get_scheduler("cosine", num_warmup_steps=W,
// num_training_steps=N) (get_cosine_schedule_with_warmup, num_cycles 0.5):
// the learning-rate multiplier of optimizer step `step` (0-based): step / W
// during warm-up (0 at step 0, as the authors' runs start), then
// 0.5 * (1 + cos(pi * (step - W) / (N - W))), reaching 0 at N.
#ifndef FD_TRAINER_LR_SCHEDULE_H_
#define FD_TRAINER_LR_SCHEDULE_H_

#include <cstdint>

namespace fd::trainer {

double CosineWithWarmup(int64_t step, int64_t warmup_steps, int64_t total_steps);

}  // namespace fd::trainer

#endif  // FD_TRAINER_LR_SCHEDULE_H_
