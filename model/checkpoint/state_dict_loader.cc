// Strict state-dict loading; see state_dict_loader.h. Mirrors
// torch.nn.Module.load_state_dict(strict=True): collect every problem first,
// write nothing unless the whole checkpoint fits.
#include "model/checkpoint/state_dict_loader.h"

#include <torch/torch.h>

#include <algorithm>
#include <optional>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "base/status_macros.h"
#include "model/runtime/torch_call.h"

namespace fd::model {
namespace {

// One checkpoint tensor, described before its data is read.
struct SourceTensor {
  std::vector<int64_t> shape;
  torch::ScalarType dtype = torch::kFloat32;
  std::function<absl::StatusOr<torch::Tensor>()> read;
};

std::string ShapeString(torch::IntArrayRef shape) {
  return absl::StrCat("[", absl::StrJoin(shape, ", "), "]");
}

// Floating point and integer/bool values are not interchangeable: loading a
// float into an int64 buffer (or the reverse) means the checkpoint is wrong.
bool SameDtypeKind(torch::ScalarType a, torch::ScalarType b) {
  return c10::isFloatingType(a) == c10::isFloatingType(b) &&
         c10::isComplexType(a) == c10::isComplexType(b);
}

// "3 missing keys: [a, b, c]" with at most `max_listed` names.
void AppendProblem(const char* what_singular, const char* what_plural,
                   const std::vector<std::string>& items, size_t max_listed,
                   std::vector<std::string>* parts) {
  if (items.empty()) return;
  const size_t listed = std::min(items.size(), std::max<size_t>(max_listed, 1));
  std::string text =
      absl::StrCat(items.size(), " ", items.size() == 1 ? what_singular : what_plural, ": [",
                   absl::StrJoin(items.begin(), items.begin() + listed, ", "));
  if (listed < items.size()) absl::StrAppend(&text, ", ... and ", items.size() - listed, " more");
  absl::StrAppend(&text, "]");
  parts->push_back(std::move(text));
}

absl::Status LoadImpl(torch::nn::Module& module, const std::map<std::string, SourceTensor>& source,
                      const LoadOptions& options, const std::string& source_name) {
  // Targets: parameters and buffers by their dotted names.
  std::map<std::string, torch::Tensor> targets;
  for (const auto& item : module.named_parameters(/*recurse=*/true)) {
    targets.emplace(item.key(), item.value());
  }
  for (const auto& item : module.named_buffers(/*recurse=*/true)) {
    targets.emplace(item.key(), item.value());
  }

  std::vector<std::string> unexpected;
  std::vector<std::string> mismatched;
  std::vector<std::string> dtype_mismatched;
  // target name -> checkpoint key.
  std::map<std::string, std::string> matched;
  // Tensors an adapt_shape hook produced (read in the validation pass).
  std::map<std::string, torch::Tensor> adapted;

  for (const auto& [key, tensor] : source) {
    const std::string name = options.rename_key ? options.rename_key(key) : key;
    if (name.empty()) continue;
    const auto target_it = targets.find(name);
    if (target_it == targets.end()) {
      if (!(options.ignore_unexpected && options.ignore_unexpected(key))) {
        unexpected.push_back(name == key ? key : absl::StrCat(key, " (as ", name, ")"));
      }
      continue;
    }
    if (const auto [it, inserted] = matched.emplace(name, key); !inserted) {
      return absl::InvalidArgumentError(absl::StrCat("loading '", source_name, "': keys '",
                                                     it->second, "' and '", key, "' both map to '",
                                                     name, "'"));
    }
    const torch::Tensor& target = target_it->second;
    if (!SameDtypeKind(tensor.dtype, target.scalar_type())) {
      dtype_mismatched.push_back(absl::StrCat(name, ": checkpoint ", c10::toString(tensor.dtype),
                                              " vs module ", c10::toString(target.scalar_type())));
      continue;
    }
    if (torch::IntArrayRef(tensor.shape) == target.sizes()) continue;
    if (options.adapt_shape) {
      FD_ASSIGN_OR_RETURN(torch::Tensor loaded, tensor.read());
      FD_ASSIGN_OR_RETURN(torch::Tensor result, TorchCall("LoadStateDict adapt_shape", [&]() {
                            return options.adapt_shape(name, std::move(loaded), target);
                          }));
      if (result.defined() && result.sizes() == target.sizes()) {
        adapted.emplace(name, std::move(result));
        continue;
      }
    }
    mismatched.push_back(absl::StrCat(name, ": checkpoint ", ShapeString(tensor.shape),
                                      " vs module ", ShapeString(target.sizes())));
  }

  std::vector<std::string> missing;
  for (const auto& [name, target] : targets) {
    if (matched.count(name) != 0) continue;
    if (options.allow_missing && options.allow_missing(name)) continue;
    missing.push_back(name);
  }

  std::vector<std::string> parts;
  AppendProblem("missing key", "missing keys", missing, options.max_listed, &parts);
  AppendProblem("unexpected key", "unexpected keys", unexpected, options.max_listed, &parts);
  AppendProblem("shape mismatch", "shape mismatches", mismatched, options.max_listed, &parts);
  AppendProblem("dtype mismatch", "dtype mismatches", dtype_mismatched, options.max_listed, &parts);
  if (!parts.empty()) {
    return absl::InvalidArgumentError(absl::StrCat("loading '", source_name, "' into ",
                                                   module.name(),
                                                   " (strict): ", absl::StrJoin(parts, "; ")));
  }

  // Everything fits: copy, converting dtype and device.
  return TorchCall("LoadStateDict", [&]() -> absl::Status {
    torch::NoGradGuard no_grad;
    for (const auto& [name, key] : matched) {
      torch::Tensor target = targets.at(name);
      torch::Tensor value;
      if (auto it = adapted.find(name); it != adapted.end()) {
        value = it->second;
      } else {
        FD_ASSIGN_OR_RETURN(value, source.at(key).read());
      }
      target.copy_(value);
    }
    return absl::OkStatus();
  });
}

}  // namespace

absl::Status LoadStateDict(torch::nn::Module& module, const SafetensorsFile& file,
                           const LoadOptions& options) {
  std::map<std::string, SourceTensor> source;
  for (const std::string& key : file.Keys()) {
    FD_ASSIGN_OR_RETURN(const SafetensorsFile::TensorInfo info, file.Info(key));
    source.emplace(key, SourceTensor{info.shape, info.scalar_type,
                                     [&file, key = key] { return file.Get(key); }});
  }
  return LoadImpl(module, source, options, file.path());
}

absl::Status LoadStateDict(torch::nn::Module& module,
                           const std::map<std::string, torch::Tensor>& tensors,
                           const LoadOptions& options, const std::string& source_name) {
  std::map<std::string, SourceTensor> source;
  for (const auto& entry : tensors) {
    // A reference to the map's tensor, not a structured binding: C++17 does
    // not let a lambda capture a binding (GCC allows it, clang does not).
    const torch::Tensor& tensor = entry.second;
    if (!tensor.defined()) {
      return absl::InvalidArgumentError(
          absl::StrCat("loading '", source_name, "': tensor '", entry.first, "' is undefined"));
    }
    source.emplace(entry.first,
                   SourceTensor{tensor.sizes().vec(), tensor.scalar_type(),
                                [&tensor]() -> absl::StatusOr<torch::Tensor> { return tensor; }});
  }
  return LoadImpl(module, source, options, source_name);
}

}  // namespace fd::model
