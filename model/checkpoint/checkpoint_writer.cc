// Checkpoint folders in the diffusers layout; see checkpoint_writer.h.
#include "model/checkpoint/checkpoint_writer.h"

#include <fcntl.h>
#include <torch/torch.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <memory>
#include <system_error>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "base/status_macros.h"
#include "model/checkpoint/safetensors.h"
#include "model/lora/lora_layers.h"
#include "model/runtime/torch_call.h"

namespace fd::model {

namespace fs = std::filesystem;

const char kSd15SchedulerConfigJson[] = R"({
  "_class_name": "PNDMScheduler",
  "_diffusers_version": "0.6.0",
  "beta_end": 0.012,
  "beta_schedule": "scaled_linear",
  "beta_start": 0.00085,
  "clip_sample": false,
  "num_train_timesteps": 1000,
  "set_alpha_to_one": false,
  "skip_prk_steps": true,
  "steps_offset": 1,
  "trained_betas": null
}
)";

absl::Status WriteFileAtomically(const std::string& path, std::string_view bytes) {
  static std::atomic<uint64_t> counter{0};
  const std::string temp = absl::StrCat(path, ".tmp.", ::getpid(), ".", counter.fetch_add(1));
  std::FILE* out = std::fopen(temp.c_str(), "wb");
  if (out == nullptr) {
    return absl::InternalError(absl::StrCat("cannot create '", temp, "': ", std::strerror(errno)));
  }
  bool ok = std::fwrite(bytes.data(), 1, bytes.size(), out) == bytes.size();
  ok = ok && std::fflush(out) == 0 && ::fsync(::fileno(out)) == 0;
  const int saved_errno = errno;
  ok = (std::fclose(out) == 0) && ok;
  if (ok && std::rename(temp.c_str(), path.c_str()) == 0) return absl::OkStatus();
  const int error = ok ? errno : saved_errno;
  std::remove(temp.c_str());
  return absl::InternalError(absl::StrCat("cannot write '", path, "': ", std::strerror(error)));
}

absl::Status CreateDirectories(const std::string& dir) {
  std::error_code error;
  fs::create_directories(dir, error);
  if (error) {
    return absl::InternalError(absl::StrCat("cannot create '", dir, "': ", error.message()));
  }
  return absl::OkStatus();
}

absl::Status SyncDirectory(const std::string& dir) {
  const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY);
  if (fd < 0) {
    return absl::InternalError(absl::StrCat("cannot open '", dir, "': ", std::strerror(errno)));
  }
  const bool ok = ::fsync(fd) == 0;
  const int error = errno;
  ::close(fd);
  if (!ok) {
    return absl::InternalError(absl::StrCat("cannot sync '", dir, "': ", std::strerror(error)));
  }
  return absl::OkStatus();
}

absl::Status WriteSafetensorsFile(const std::string& path,
                                  const std::map<std::string, torch::Tensor>& tensors) {
  return SaveSafetensors(path, tensors, {{"format", "pt"}});
}

absl::Status WriteModelFolder(torch::nn::Module& module, const std::string& config_text,
                              const std::string& dir, torch::Dtype dtype) {
  if (dtype != torch::kFloat32 && dtype != torch::kFloat16 && dtype != torch::kBFloat16) {
    return absl::InvalidArgumentError("weights must be stored as float32, float16 or bfloat16");
  }
  FD_RETURN_IF_ERROR(CreateDirectories(dir));
  FD_RETURN_IF_ERROR(WriteFileAtomically((fs::path(dir) / "config.json").string(), config_text));
  std::map<std::string, torch::Tensor> tensors;
  FD_RETURN_IF_ERROR(TorchCall("WriteModelFolder", [&]() -> absl::Status {
    torch::NoGradGuard no_grad;
    for (const auto& item : module.named_parameters()) {
      tensors[item.key()] = item.value().detach().to(dtype);
    }
    return absl::OkStatus();
  }));
  return WriteSafetensorsFile((fs::path(dir) / "diffusion_pytorch_model.safetensors").string(),
                              tensors);
}

bool IsFullSkipAttnTarget(const std::string& name) {
  for (const char* skipped : {"to_q", "to_k", "to_v", "to_out.0"}) {
    if (name == skipped || absl::EndsWith(name, absl::StrCat(".", skipped))) return false;
  }
  return true;
}

absl::StatusOr<std::map<std::string, torch::Tensor>> LiveLoraStateDict(torch::nn::Module& unet,
                                                                       torch::Dtype dtype) {
  std::map<std::string, torch::Tensor> tensors;
  for (const auto& item : unet.named_modules(/*name_prefix=*/"", /*include_self=*/false)) {
    auto* layer = dynamic_cast<LoraAdaptable*>(item.value().get());
    if (layer == nullptr || !layer->has_live_adapters()) continue;
    const std::vector<LiveLoraAdapter>& adapters = layer->live_adapters();
    if (adapters.size() != 1 || adapters[0].scaling != 1.0) {
      return absl::InvalidArgumentError(absl::StrCat(
          "module '", item.key(), "': a LoRA file holds one adapter with alpha = rank per module"));
    }
    FD_RETURN_IF_ERROR(TorchCall("LiveLoraStateDict", [&]() -> absl::Status {
      const std::string prefix = absl::StrCat("unet.", item.key());
      tensors[prefix + ".lora_A.weight"] = adapters[0].down.detach().to(dtype);
      tensors[prefix + ".lora_B.weight"] = adapters[0].up.detach().to(dtype);
      return absl::OkStatus();
    }));
  }
  return tensors;
}

}  // namespace fd::model
