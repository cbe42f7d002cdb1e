#include "trainer/lr_schedule.h"

#include <algorithm>
#include <cmath>

namespace fd::trainer {

double CosineWithWarmup(int64_t step, int64_t warmup_steps, int64_t total_steps) {
  if (step < warmup_steps) {
    return static_cast<double>(step) / static_cast<double>(std::max<int64_t>(1, warmup_steps));
  }
  const double progress = static_cast<double>(step - warmup_steps) /
                          static_cast<double>(std::max<int64_t>(1, total_steps - warmup_steps));
  constexpr double kNumCycles = 0.5;  // get_scheduler does not forward num_cycles
  return std::max(0.0, 0.5 * (1.0 + std::cos(M_PI * 2.0 * kNumCycles * progress)));
}

}  // namespace fd::trainer
