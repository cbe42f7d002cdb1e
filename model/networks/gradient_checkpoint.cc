// Reentrant gradient checkpointing for LibTorch, after PyTorch's
// torch/utils/checkpoint.py CheckpointFunction (forward under no_grad saving
// the inputs; backward re-running the function with grad enabled on detached
// copies of them and calling torch.autograd.backward on its output).
#include "model/networks/gradient_checkpoint.h"

#include <torch/autograd.h>
#include <torch/torch.h>

#include <utility>

namespace fd::model {
namespace {

// AutogradContext::saved_data holds IValues; a capsule carries the C++
// function (and where the undefined inputs were) from forward to backward.
struct CheckpointedCall : torch::CustomClassHolder {
  CheckpointedFunction function;
  std::vector<bool> defined;  // per original input: passed through autograd
};

// The function's input list from the defined tensors (undefined elsewhere).
std::vector<torch::Tensor> Expand(const CheckpointedCall& call,
                                  const std::vector<torch::Tensor>& defined_inputs) {
  std::vector<torch::Tensor> inputs(call.defined.size());
  size_t next = 0;
  for (size_t i = 0; i < inputs.size(); ++i) {
    if (call.defined[i]) inputs[i] = defined_inputs[next++];
  }
  return inputs;
}

// PyTorch's CheckpointFunction (use_reentrant=True).
struct CheckpointFunction : public torch::autograd::Function<CheckpointFunction> {
  // Runs with grad mode off (Function::apply): no graph, no activations.
  static torch::Tensor forward(torch::autograd::AutogradContext* ctx,
                               const c10::intrusive_ptr<CheckpointedCall>& call,
                               at::TensorList inputs) {
    ctx->saved_data["call"] = c10::IValue::make_capsule(call);
    ctx->save_for_backward(inputs.vec());
    return call->function(Expand(*call, inputs.vec()));
  }

  // Gradients: none for the call, then one per defined input.
  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx,
                                                 torch::autograd::variable_list grad_outputs) {
    const auto call =
        c10::static_intrusive_pointer_cast<CheckpointedCall>(ctx->saved_data["call"].toCapsule());
    const torch::autograd::variable_list saved = ctx->get_saved_variables();
    std::vector<torch::Tensor> detached;
    detached.reserve(saved.size());
    for (size_t i = 0; i < saved.size(); ++i) {
      // Leaves of the recomputed graph: their .grad is the input gradient.
      detached.push_back(saved[i].detach().requires_grad_(ctx->needs_input_grad(i)));
    }
    torch::Tensor output;
    {
      torch::AutoGradMode enable_grad(true);
      output = call->function(Expand(*call, detached));
    }
    // Accumulates into the parameters' .grad and the detached inputs' .grad.
    if (output.requires_grad() && grad_outputs[0].defined()) {
      torch::autograd::backward({output}, {grad_outputs[0]});
    }
    torch::autograd::variable_list grads;
    grads.reserve(detached.size() + 1);
    grads.emplace_back();  // the call is not a tensor
    for (const torch::Tensor& input : detached) {
      grads.push_back(input.requires_grad() ? input.grad() : torch::Tensor());
    }
    return grads;
  }
};

}  // namespace

torch::Tensor Checkpoint(CheckpointedFunction function, const std::vector<torch::Tensor>& inputs) {
  bool any_input_requires_grad = false;
  for (const torch::Tensor& input : inputs) {
    any_input_requires_grad = any_input_requires_grad || (input.defined() && input.requires_grad());
  }
  // Without an input that needs a gradient the autograd node would not be
  // recorded, and the parameters inside would get no gradient (PyTorch's
  // reentrant checkpoint only warns then): run it plainly instead.
  if (!torch::GradMode::is_enabled() || !any_input_requires_grad) return function(inputs);
  auto call = c10::make_intrusive<CheckpointedCall>();
  call->function = std::move(function);
  std::vector<torch::Tensor> defined_inputs;
  for (const torch::Tensor& input : inputs) {
    call->defined.push_back(input.defined());
    if (input.defined()) defined_inputs.push_back(input);
  }
  return CheckpointFunction::apply(call, at::TensorList(defined_inputs));
}

bool GradientCheckpointable::ShouldCheckpoint() const {
  return gradient_checkpointing_ && torch::GradMode::is_enabled();
}

int SetGradientCheckpointing(torch::nn::Module& root, bool enabled) {
  int set = 0;
  auto visit = [&](torch::nn::Module& module) {
    if (auto* checkpointable = dynamic_cast<GradientCheckpointable*>(&module)) {
      checkpointable->set_gradient_checkpointing(enabled);
      ++set;
    }
  };
  visit(root);
  for (const std::shared_ptr<torch::nn::Module>& module : root.modules(/*include_self=*/false)) {
    visit(*module);
  }
  return set;
}

}  // namespace fd::model
