#include "model/runtime/batch_invariance.h"

namespace fd::model {
namespace {

thread_local bool batch_invariant = false;

}  // namespace

BatchInvariantScope::BatchInvariantScope(bool enabled) : previous_(batch_invariant) {
  batch_invariant = previous_ || enabled;
}

BatchInvariantScope::~BatchInvariantScope() { batch_invariant = previous_; }

bool BatchInvariantScope::Active() { return batch_invariant; }

}  // namespace fd::model
