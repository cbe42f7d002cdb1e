// LoRA file parsing and delta math; see lora_file.h.
#include "model/lora/lora_file.h"

#include <torch/torch.h>

#include <cmath>
#include <cstring>
#include <memory>
#include <optional>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "base/status_macros.h"
#include "model/runtime/torch_call.h"

namespace fd::model {
namespace {

enum class Part { kDown, kUp, kAlpha };

struct ParsedKey {
  std::string module;
  Part part = Part::kDown;
  const char* format = "";  // "PEFT" or "diffusers" for down/up
};

struct KeySuffix {
  const char* suffix;
  Part part;
  const char* format;
};

constexpr KeySuffix kSuffixes[] = {
    {".lora_A.weight", Part::kDown, "PEFT"},
    {".lora_B.weight", Part::kUp, "PEFT"},
    {".lora.down.weight", Part::kDown, "diffusers"},
    {".lora.up.weight", Part::kUp, "diffusers"},
    {".alpha", Part::kAlpha, ""},
};

bool StartsWith(const std::string& text, const std::string& prefix) {
  return text.compare(0, prefix.size(), prefix) == 0;
}

bool EndsWith(const std::string& text, const std::string& suffix) {
  return text.size() >= suffix.size() &&
         text.compare(text.size() - suffix.size(), suffix.size(), suffix) == 0;
}

std::string ShapeString(const torch::Tensor& tensor) {
  return absl::StrCat("[", absl::StrJoin(tensor.sizes(), ", "), "]");
}

absl::Status KeyError(const std::string& source, const std::string& key, const std::string& what) {
  return absl::InvalidArgumentError(
      absl::StrCat("LoRA file '", source, "', key '", key, "': ", what));
}

absl::StatusOr<ParsedKey> ParseKey(const std::string& key, const std::string& source) {
  std::string rest = key;
  if (StartsWith(rest, "unet.")) {
    rest = rest.substr(5);
  } else {
    for (const char* other : {"text_encoder.", "text_encoder_2.", "transformer.", "controlnet."}) {
      if (StartsWith(rest, other)) {
        return KeyError(source, key,
                        absl::StrCat("LoRA for '", std::string(other, std::strlen(other) - 1),
                                     "' is not supported (only the UNet's)"));
      }
    }
  }
  for (const KeySuffix& suffix : kSuffixes) {
    if (EndsWith(rest, suffix.suffix) && rest.size() > std::strlen(suffix.suffix)) {
      return ParsedKey{rest.substr(0, rest.size() - std::strlen(suffix.suffix)), suffix.part,
                       suffix.format};
    }
  }
  return KeyError(source, key,
                  "not a LoRA key (expected [unet.]<module>.lora_A.weight / .lora_B.weight, "
                  ".lora.down.weight / .lora.up.weight or .alpha)");
}

// The halves of one module as found in the file.
struct ModuleEntry {
  torch::Tensor down, up, alpha;
  std::string down_key, up_key, alpha_key;
  const char* format = "";
};

// Checks one module's pair and turns it into LoraModuleWeights.
absl::StatusOr<LoraModuleWeights> BuildModule(const std::string& source, const std::string& module,
                                              const ModuleEntry& entry) {
  if (!entry.down.defined() || !entry.up.defined()) {
    if (!entry.down.defined() && !entry.up.defined()) {
      return KeyError(source, entry.alpha_key, "alpha without lora down/up weights");
    }
    const bool peft = std::string(entry.format) == "PEFT";
    const std::string present = entry.down.defined() ? entry.down_key : entry.up_key;
    const std::string missing = absl::StrCat(
        module, entry.down.defined() ? (peft ? ".lora_B.weight" : ".lora.up.weight")
                                     : (peft ? ".lora_A.weight" : ".lora.down.weight"));
    return KeyError(source, present, absl::StrCat("has no partner: '", missing, "' is missing"));
  }
  for (const auto& [tensor, key] :
       {std::pair{&entry.down, &entry.down_key}, std::pair{&entry.up, &entry.up_key}}) {
    if (!tensor->is_floating_point()) {
      return KeyError(
          source, *key,
          absl::StrCat("dtype ", c10::toString(tensor->scalar_type()), " is not floating point"));
    }
  }
  const torch::Tensor& a = entry.down;
  const torch::Tensor& b = entry.up;
  const bool linear = a.dim() == 2 && b.dim() == 2;
  const bool conv = a.dim() == 4 && b.dim() == 4 && b.size(2) == 1 && b.size(3) == 1;
  if (!linear && !conv) {
    return KeyError(source, entry.down_key,
                    absl::StrCat("shapes down ", ShapeString(a), " / up ", ShapeString(b),
                                 " are neither Linear (A [r, in], B [out, r]) nor Conv2d "
                                 "(A [r, in, kh, kw], B [out, r, 1, 1])"));
  }
  if (a.size(0) <= 0 || a.size(0) != b.size(1)) {
    return KeyError(source, entry.down_key,
                    absl::StrCat("rank mismatch: down ", ShapeString(a), " has rank ", a.size(0),
                                 ", up ", ShapeString(b), " has rank ", b.size(1)));
  }
  LoraModuleWeights weights;
  weights.down = a;
  weights.up = b;
  weights.rank = a.size(0);
  weights.alpha = static_cast<double>(weights.rank);
  if (entry.alpha.defined()) {
    if (entry.alpha.numel() != 1 || entry.alpha.is_complex() ||
        entry.alpha.scalar_type() == torch::kBool) {
      return KeyError(
          source, entry.alpha_key,
          absl::StrCat("alpha must be one number, got shape ", ShapeString(entry.alpha)));
    }
    weights.alpha = entry.alpha.to(torch::kFloat64).item<double>();
    if (!std::isfinite(weights.alpha)) {
      return KeyError(source, entry.alpha_key, "alpha is not finite");
    }
  }
  return weights;
}

// `get(key)` returns the tensor of a key.
template <typename GetTensor>
absl::StatusOr<LoraWeights> ParseImpl(const std::vector<std::string>& keys, GetTensor get,
                                      const std::string& source) {
  std::map<std::string, ModuleEntry> entries;
  for (const std::string& key : keys) {
    FD_ASSIGN_OR_RETURN(const ParsedKey parsed, ParseKey(key, source));
    FD_ASSIGN_OR_RETURN(torch::Tensor tensor, get(key));
    ModuleEntry& entry = entries[parsed.module];
    torch::Tensor* slot = nullptr;
    std::string* slot_key = nullptr;
    switch (parsed.part) {
      case Part::kDown:
        slot = &entry.down;
        slot_key = &entry.down_key;
        break;
      case Part::kUp:
        slot = &entry.up;
        slot_key = &entry.up_key;
        break;
      case Part::kAlpha:
        slot = &entry.alpha;
        slot_key = &entry.alpha_key;
        break;
    }
    if (slot->defined()) {
      return KeyError(source, key,
                      absl::StrCat("module '", parsed.module, "' already has this weight from '",
                                   *slot_key, "'"));
    }
    if (parsed.part != Part::kAlpha) {
      if (*entry.format != '\0' && std::string(entry.format) != parsed.format) {
        return KeyError(source, key,
                        absl::StrCat("mixes ", parsed.format, " and ", entry.format,
                                     " key formats for module '", parsed.module, "'"));
      }
      entry.format = parsed.format;
    }
    *slot = std::move(tensor);
    *slot_key = key;
  }

  LoraWeights weights;
  weights.source = source;
  for (const auto& [module, entry] : entries) {
    FD_ASSIGN_OR_RETURN(LoraModuleWeights module_weights, BuildModule(source, module, entry));
    weights.modules.emplace(module, std::move(module_weights));
  }
  return weights;
}

}  // namespace

std::vector<int64_t> LoraModuleWeights::WeightShape() const {
  std::vector<int64_t> shape = {up.size(0), down.size(1)};
  if (is_conv()) {
    shape.push_back(down.size(2));
    shape.push_back(down.size(3));
  }
  return shape;
}

absl::StatusOr<LoraWeights> ParseLoraWeights(const SafetensorsFile& file) {
  return ParseImpl(
      file.Keys(), [&file](const std::string& key) { return file.Get(key); }, file.path());
}

absl::StatusOr<LoraWeights> ParseLoraWeights(const std::map<std::string, torch::Tensor>& tensors,
                                             const std::string& source) {
  std::vector<std::string> keys;
  for (const auto& [key, tensor] : tensors) keys.push_back(key);
  return ParseImpl(
      keys,
      [&](const std::string& key) -> absl::StatusOr<torch::Tensor> {
        const torch::Tensor& tensor = tensors.at(key);
        if (!tensor.defined()) return KeyError(source, key, "undefined tensor");
        return tensor;
      },
      source);
}

absl::StatusOr<LoraWeights> LoadLoraWeights(const std::string& path, const FileSource& files) {
  FD_ASSIGN_OR_RETURN(std::unique_ptr<SafetensorsFile> file, files.OpenSafetensors(path));
  return ParseLoraWeights(*file);
}

absl::StatusOr<torch::Tensor> LoraDelta(const LoraModuleWeights& weights, double scale) {
  const torch::Tensor& a = weights.down;
  const torch::Tensor& b = weights.up;
  if (!a.defined() || !b.defined()) {
    return absl::InvalidArgumentError("LoraDelta: undefined down/up tensor");
  }
  const bool linear = a.dim() == 2 && b.dim() == 2;
  const bool conv = a.dim() == 4 && b.dim() == 4 && b.size(2) == 1 && b.size(3) == 1;
  if ((!linear && !conv) || a.size(0) != b.size(1) || weights.rank != a.size(0) ||
      weights.rank <= 0) {
    return absl::InvalidArgumentError(absl::StrCat("LoraDelta: inconsistent adapter: down ",
                                                   ShapeString(a), ", up ", ShapeString(b),
                                                   ", rank ", weights.rank));
  }
  return TorchCall("LoraDelta", [&]() -> absl::StatusOr<torch::Tensor> {
    const torch::ScalarType dtype =
        (a.scalar_type() == torch::kFloat64 || b.scalar_type() == torch::kFloat64)
            ? torch::kFloat64
            : torch::kFloat32;
    const torch::Tensor down = a.to(dtype);
    const torch::Tensor up = b.to(dtype);
    const double factor = scale * weights.scaling();
    if (linear) return torch::matmul(up, down).mul_(factor);  // [out, in]
    // einsum('or,rihw->oihw', B[:, :, 0, 0], A) as one matmul over the
    // flattened (in, kh, kw) axis.
    const torch::Tensor product = torch::matmul(up.flatten(1), down.flatten(1));
    return product.view({up.size(0), a.size(1), a.size(2), a.size(3)}).mul_(factor);
  });
}

}  // namespace fd::model
