// Optional recording of intermediate activations (for the golden `debug.*`
// tensors and for localising numerical differences). Networks take a
// `DebugTaps*` that is null in production; recording costs nothing then.
#ifndef FD_MODEL_NETWORKS_DEBUG_TAPS_H_
#define FD_MODEL_NETWORKS_DEBUG_TAPS_H_

#include <torch/types.h>

#include <map>
#include <string>

namespace fd::model {

// Activation name (e.g. "down_blocks.0.res_samples.1", as the goldens name
// them without the "debug." prefix) -> tensor.
using DebugTaps = std::map<std::string, torch::Tensor>;

// Records `tensor` under `name` when `taps` is not null. `name` is a
// callable returning the std::string so that it is only built when needed.
template <typename NameFn>
inline void Tap(DebugTaps* taps, NameFn&& name, const torch::Tensor& tensor) {
  if (taps != nullptr) (*taps)[name()] = tensor;
}

inline void Tap(DebugTaps* taps, const char* name, const torch::Tensor& tensor) {
  if (taps != nullptr) (*taps)[name] = tensor;
}

}  // namespace fd::model

#endif  // FD_MODEL_NETWORKS_DEBUG_TAPS_H_
