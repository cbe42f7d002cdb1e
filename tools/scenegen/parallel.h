// A minimal parallel loop over std::threads.
#ifndef FD_TOOLS_SCENEGEN_PARALLEL_H_
#define FD_TOOLS_SCENEGEN_PARALLEL_H_

#include <functional>

namespace fd::scenegen {

// Runs fn(i) for i in [0, count) on up to `threads` threads (inline when
// threads <= 1), handing out indices dynamically. fn must only write state
// owned by its index; then the result does not depend on `threads` or on
// scheduling.
void ParallelFor(int count, int threads, const std::function<void(int)>& fn);

}  // namespace fd::scenegen

#endif  // FD_TOOLS_SCENEGEN_PARALLEL_H_
