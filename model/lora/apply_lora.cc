// See apply_lora.h. The merged path follows FrameDiffuser's / PEFT's merge
// (W += scaling * B@A); the live path PEFT's LoraLayer forward.
#include "model/lora/apply_lora.h"

#include <torch/torch.h>

#include <map>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "base/status_macros.h"
#include "model/runtime/torch_call.h"

namespace fd::model {
namespace {

// At most this many problems are listed in an error message.
constexpr size_t kMaxListed = 20;

std::string ListProblems(const std::vector<std::string>& problems) {
  std::vector<std::string> shown(problems.begin(),
                                 problems.begin() + std::min(problems.size(), kMaxListed));
  std::string text = absl::StrJoin(shown, "; ");
  if (problems.size() > kMaxListed) {
    absl::StrAppend(&text, "; ... and ", problems.size() - kMaxListed, " more");
  }
  return text;
}

}  // namespace

absl::Status ApplyLora(torch::nn::Module& root, const LoraWeights& lora, LoraMode mode,
                       double scale) {
  std::map<std::string, LoraAdaptable*> layers;
  FD_RETURN_IF_ERROR(TorchCall("ApplyLora", [&]() -> absl::Status {
    for (const auto& item : root.named_modules(/*name_prefix=*/"", /*include_self=*/false)) {
      if (auto* layer = dynamic_cast<LoraAdaptable*>(item.value().get())) {
        layers[item.key()] = layer;
      }
    }
    return absl::OkStatus();
  }));

  std::vector<std::string> unmatched, misfit;
  for (const auto& [path, adapter] : lora.modules) {
    auto it = layers.find(path);
    if (it == layers.end()) {
      unmatched.push_back(path);
      continue;
    }
    absl::Status fits = it->second->CheckAdapterShapes(adapter.down, adapter.up);
    if (!fits.ok()) misfit.push_back(absl::StrCat(path, ": ", fits.message()));
  }
  if (!unmatched.empty() || !misfit.empty()) {
    std::string message = absl::StrCat("LoRA '", lora.source, "' does not fit the network:");
    if (!unmatched.empty()) {
      absl::StrAppend(&message, " ", unmatched.size(),
                      " module(s) match no Linear/Conv2d layer: ", ListProblems(unmatched), ".");
    }
    if (!misfit.empty()) {
      absl::StrAppend(&message, " ", misfit.size(),
                      " adapter(s) do not fit their layer: ", ListProblems(misfit), ".");
    }
    return absl::InvalidArgumentError(message);
  }

  for (const auto& [path, adapter] : lora.modules) {
    LoraAdaptable* layer = layers.at(path);
    if (mode == LoraMode::kMerged) {
      FD_ASSIGN_OR_RETURN(torch::Tensor delta, LoraDelta(adapter, scale));
      FD_RETURN_IF_ERROR(layer->MergeDelta(delta));
    } else {
      FD_RETURN_IF_ERROR(layer->AddLiveAdapter(adapter.down, adapter.up, adapter.scaling()));
    }
  }
  if (mode == LoraMode::kLive) SetLoraScale(root, scale);
  return absl::OkStatus();
}

}  // namespace fd::model
