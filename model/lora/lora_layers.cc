// LoRA-capable Linear / Conv2d; see lora_layers.h. The live forward follows
// PEFT's tuners/lora/layer.py (Linear.forward / Conv2d.forward):
// result = base(x) + lora_B(lora_A(x)) * scaling.
#include "model/lora/lora_layers.h"

#include <torch/torch.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "base/status_macros.h"
#include "model/runtime/batch_invariance.h"
#include "model/runtime/conv2d_kernel.h"
#include "model/runtime/torch_call.h"

namespace fd::model {
namespace {

std::string ShapeOf(const torch::Tensor& t) {
  return absl::StrCat("[", absl::StrJoin(t.sizes().vec(), ", "), "]");
}

// forward_one over the batch (dim 0) of x: in one call, or, inside a
// BatchInvariantScope, sample by sample (see model/runtime/batch_invariance.h).
template <typename ForwardOne>
torch::Tensor PerSampleIfInvariant(const torch::Tensor& x, ForwardOne&& forward_one) {
  if (x.dim() < 2 || x.size(0) < 2 || !BatchInvariantScope::Active()) return forward_one(x);
  std::vector<torch::Tensor> samples;
  samples.reserve(x.size(0));
  for (int64_t i = 0; i < x.size(0); ++i) samples.push_back(forward_one(x.slice(0, i, i + 1)));
  return torch::cat(samples, 0);
}

}  // namespace

absl::Status LoraAdaptable::MergeDelta(const torch::Tensor& delta) {
  torch::Tensor& w = base_weight();
  if (!delta.defined() || delta.sizes() != w.sizes()) {
    return absl::InvalidArgumentError(absl::StrCat("LoRA delta of shape ",
                                                   delta.defined() ? ShapeOf(delta) : "undefined",
                                                   " does not fit a weight of shape ", ShapeOf(w)));
  }
  return TorchCall("MergeDelta", [&]() -> absl::Status {
    torch::NoGradGuard no_grad;
    torch::Tensor merged = w.to(torch::kFloat32) + delta.to(w.device(), torch::kFloat32);
    w.copy_(merged.to(w.scalar_type()));
    return absl::OkStatus();
  });
}

absl::Status LoraAdaptable::AddLiveAdapter(const torch::Tensor& down, const torch::Tensor& up,
                                           double scaling) {
  FD_RETURN_IF_ERROR(CheckAdapterShapes(down, up));
  return TorchCall("AddLiveAdapter", [&]() -> absl::Status {
    const torch::Tensor& w = base_weight();
    live_.push_back({down.to(w.options()).contiguous(), up.to(w.options()).contiguous(), scaling});
    return absl::OkStatus();
  });
}

// ---------------------------------------------------------------------------

LoraLinearImpl::LoraLinearImpl(int64_t in_features, int64_t out_features, bool bias)
    : in_features_(in_features), out_features_(out_features) {
  // Zero until a checkpoint is loaded (loading is strict, so every parameter
  // is overwritten); zeros rather than uninitialised memory.
  weight = register_parameter("weight", torch::zeros({out_features, in_features}));
  if (bias) this->bias = register_parameter("bias", torch::zeros({out_features}));
}

torch::Tensor LoraLinearImpl::forward(const torch::Tensor& x) {
  return PerSampleIfInvariant(x, [this](const torch::Tensor& in) {
    torch::Tensor y = torch::linear(in, weight, bias);  // [..., out]
    for (const LiveLoraAdapter& a : live_) {
      // Adapters follow the input if the layer was moved after attaching them.
      torch::Tensor down = a.down.to(in.options());
      torch::Tensor up = a.up.to(in.options());
      y = y + torch::linear(torch::linear(in, down), up) * (lora_scale_ * a.scaling);
    }
    return y;
  });
}

absl::Status LoraLinearImpl::CheckAdapterShapes(const torch::Tensor& down,
                                                const torch::Tensor& up) const {
  if (down.dim() != 2 || up.dim() != 2 || down.size(1) != in_features_ ||
      up.size(0) != out_features_ || up.size(1) != down.size(0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("LoRA adapter shapes down ", ShapeOf(down), " / up ", ShapeOf(up),
                     " do not fit Linear(", in_features_, ", ", out_features_,
                     "): expected down [r, ", in_features_, "] and up [", out_features_, ", r]"));
  }
  return absl::OkStatus();
}

// ---------------------------------------------------------------------------

LoraConv2dImpl::LoraConv2dImpl(int64_t in_channels, int64_t out_channels, int64_t kernel_size,
                               int64_t stride, int64_t padding, bool bias)
    : in_channels_(in_channels),
      out_channels_(out_channels),
      kernel_size_(kernel_size),
      stride_(stride),
      padding_(padding) {
  weight = register_parameter("weight",
                              torch::zeros({out_channels, in_channels, kernel_size, kernel_size}));
  if (bias) this->bias = register_parameter("bias", torch::zeros({out_channels}));
}

torch::Tensor LoraConv2dImpl::forward(const torch::Tensor& x) {
  return PerSampleIfInvariant(x, [this](const torch::Tensor& in) {
    // in: [N, in, H, W] -> y: [N, out, H', W']
    torch::Tensor y = Conv2dForward(in, weight, bias, stride_, padding_);
    for (const LiveLoraAdapter& a : live_) {
      torch::Tensor down = a.down.to(in.options());
      torch::Tensor up = a.up.to(in.options());
      // lora_A: Conv2d(in, r, k, stride, padding); lora_B: Conv2d(r, out, 1).
      torch::Tensor h = Conv2dForward(in, down, {}, stride_, padding_);  // [N, r, H', W']
      y = y + Conv2dForward(h, up, {}, 1, 0) * (lora_scale_ * a.scaling);
    }
    return y;
  });
}

absl::Status LoraConv2dImpl::CheckAdapterShapes(const torch::Tensor& down,
                                                const torch::Tensor& up) const {
  if (down.dim() != 4 || up.dim() != 4 || down.size(1) != in_channels_ ||
      down.size(2) != kernel_size_ || down.size(3) != kernel_size_ || up.size(0) != out_channels_ ||
      up.size(1) != down.size(0) || up.size(2) != 1 || up.size(3) != 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("LoRA adapter shapes down ", ShapeOf(down), " / up ", ShapeOf(up),
                     " do not fit Conv2d(", in_channels_, ", ", out_channels_, ", kernel ",
                     kernel_size_, "): expected down [r, ", in_channels_, ", ", kernel_size_, ", ",
                     kernel_size_, "] and up [", out_channels_, ", r, 1, 1]"));
  }
  return absl::OkStatus();
}

// ---------------------------------------------------------------------------

namespace {

template <typename Fn>
void ForEachAdaptable(torch::nn::Module& root, Fn&& fn) {
  for (const std::shared_ptr<torch::nn::Module>& m : root.modules(/*include_self=*/true)) {
    if (auto* adaptable = dynamic_cast<LoraAdaptable*>(m.get())) fn(*adaptable);
  }
}

}  // namespace

void SetLoraScale(torch::nn::Module& root, double scale) {
  ForEachAdaptable(root, [scale](LoraAdaptable& layer) { layer.set_lora_scale(scale); });
}

void RemoveLiveLora(torch::nn::Module& root) {
  ForEachAdaptable(root, [](LoraAdaptable& layer) { layer.RemoveLiveAdapters(); });
}

}  // namespace fd::model
