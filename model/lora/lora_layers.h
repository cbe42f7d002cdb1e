// Linear and Conv2d layers that can carry LoRA adapters (see apply_lora.h for
// attaching a LoRA file's adapters to a network).
//
// They replace torch.nn.Linear / torch.nn.Conv2d in every network of fd::model
// and behave exactly like them (parameters `weight` and `bias`, so the
// checkpoint keys do not change). A LoRA adapter (PEFT's tuners/lora/layer.py
// LoraLayer: lora_A = the "down" projection, lora_B = the "up" projection) can
// be used in two ways:
//  * merged (the default; zero runtime cost): W' = W + scale * (alpha/r) * B@A
//    (conv: einsum('or,rihw->oihw', B[:, :, 0, 0], A)); biases unchanged.
//  * live (unmerged): y = base(x) + B(A(x)) * (scale * alpha/r), the scale can
//    be changed at any time with SetLoraScale (PEFT's set_scale).
// Adapter tensors are plain members, never registered parameters or buffers:
// named_parameters() / named_buffers() of a network stay its checkpoint keys.
#ifndef FD_MODEL_LORA_LORA_LAYERS_H_
#define FD_MODEL_LORA_LORA_LAYERS_H_

#include <torch/nn/module.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"

namespace fd::model {

// One unmerged adapter of a layer. `down` is lora_A ([r, in] or
// [r, in, kh, kw]), `up` is lora_B ([out, r] or [out, r, 1, 1]);
// `scaling` = alpha / r, multiplied by the adapter scale at run time.
struct LiveLoraAdapter {
  torch::Tensor down;
  torch::Tensor up;
  double scaling = 1.0;
};

// Shared by LoraLinearImpl and LoraConv2dImpl: the live adapters and their
// scale. Not thread-safe to modify while a forward runs.
class LoraAdaptable {
 public:
  virtual ~LoraAdaptable() = default;

  // The base weight (the registered `weight` parameter).
  virtual torch::Tensor& base_weight() = 0;
  // INVALID_ARGUMENT if the adapter shapes do not fit this layer.
  virtual absl::Status CheckAdapterShapes(const torch::Tensor& down,
                                          const torch::Tensor& up) const = 0;

  // Merges a full-rank weight delta (lora_file.h LoraDelta: scale * alpha/r *
  // B@A): W += delta, added in float32 and rounded once to the weight's
  // dtype. Errors: INVALID_ARGUMENT (delta shape != weight shape), INTERNAL.
  absl::Status MergeDelta(const torch::Tensor& delta);
  // Keeps the adapter unmerged (converted to the weight's device and dtype).
  // Errors: INVALID_ARGUMENT (shapes), INTERNAL (torch).
  absl::Status AddLiveAdapter(const torch::Tensor& down, const torch::Tensor& up, double scaling);
  void RemoveLiveAdapters() { live_.clear(); }
  bool has_live_adapters() const { return !live_.empty(); }
  // The live adapters in the order they were added. The trainer makes their
  // tensors trainable (requires_grad) in place: the forward uses them as
  // they are, so gradients reach them (model/lora_training.h).
  const std::vector<LiveLoraAdapter>& live_adapters() const { return live_; }
  std::vector<LiveLoraAdapter>& mutable_live_adapters() { return live_; }
  // PEFT set_scale: the live adapters contribute scale * alpha/r.
  void set_lora_scale(double scale) { lora_scale_ = scale; }
  double lora_scale() const { return lora_scale_; }

 protected:
  std::vector<LiveLoraAdapter> live_;
  double lora_scale_ = 1.0;
};

// torch.nn.Linear(in_features, out_features, bias) with optional adapters.
class LoraLinearImpl : public torch::nn::Module, public LoraAdaptable {
 public:
  LoraLinearImpl(int64_t in_features, int64_t out_features, bool bias = true);

  // x: [..., in_features] -> [..., out_features]. Inside a
  // BatchInvariantScope, each slice of dim 0 runs alone (batch_invariance.h).
  torch::Tensor forward(const torch::Tensor& x);

  torch::Tensor& base_weight() override { return weight; }
  absl::Status CheckAdapterShapes(const torch::Tensor& down,
                                  const torch::Tensor& up) const override;

  int64_t in_features() const { return in_features_; }
  int64_t out_features() const { return out_features_; }

  torch::Tensor weight;  // [out, in]
  torch::Tensor bias;    // [out] or undefined

 private:
  int64_t in_features_;
  int64_t out_features_;
};
TORCH_MODULE(LoraLinear);

// torch.nn.Conv2d(in, out, kernel_size, stride, padding, bias=True) with
// square kernels, strides and paddings, and optional adapters.
class LoraConv2dImpl : public torch::nn::Module, public LoraAdaptable {
 public:
  LoraConv2dImpl(int64_t in_channels, int64_t out_channels, int64_t kernel_size, int64_t stride = 1,
                 int64_t padding = 0, bool bias = true);

  // x: [N, in, H, W] -> [N, out, H', W']. Inside a BatchInvariantScope,
  // each sample runs alone (batch_invariance.h).
  torch::Tensor forward(const torch::Tensor& x);

  torch::Tensor& base_weight() override { return weight; }
  absl::Status CheckAdapterShapes(const torch::Tensor& down,
                                  const torch::Tensor& up) const override;

  int64_t in_channels() const { return in_channels_; }
  int64_t out_channels() const { return out_channels_; }
  int64_t kernel_size() const { return kernel_size_; }

  torch::Tensor weight;  // [out, in, k, k]
  torch::Tensor bias;    // [out] or undefined

 private:
  int64_t in_channels_;
  int64_t out_channels_;
  int64_t kernel_size_;
  int64_t stride_;
  int64_t padding_;
};
TORCH_MODULE(LoraConv2d);

// Sets the live-adapter scale of every layer of `root` (PEFT set_scale /
// FrameDiffuser's set_extra_condition_scale). No effect on merged adapters.
// Not thread-safe: no forward may run on `root` meanwhile.
void SetLoraScale(torch::nn::Module& root, double scale);

// Drops all live adapters of `root` (merged ones stay merged).
void RemoveLiveLora(torch::nn::Module& root);

}  // namespace fd::model

#endif  // FD_MODEL_LORA_LORA_LAYERS_H_
