// See attention_kernel.h: operand checks, the instruction-set choice and the
// threads around the fused loop of attention_rows_impl.h.
#include "model/runtime/attention_kernel.h"

#include <ATen/Parallel.h>
#include <torch/torch.h>

#include <atomic>
#include <cstdlib>
#include <cstring>
#include <vector>

#include "model/runtime/attention_rows.h"

namespace fd::model {
namespace {

static_assert(kMaxFusedAttentionHeadDim == attention_rows::kMaxHeadDim,
              "the public limit is the loop's register count");

enum class Isa { kNone, kAvx2, kAvx512 };

std::atomic<bool> enabled{true};

// The widest instruction set both the CPU and the build have, capped like
// ATen's own kernels by ATEN_CPU_CAPABILITY.
Isa ChooseIsa() {
#if defined(FD_FUSED_ATTENTION_KERNELS) && (defined(__x86_64__) || defined(__i386__))
  __builtin_cpu_init();
  const char* cap = std::getenv("ATEN_CPU_CAPABILITY");
  const bool capped_avx2 = cap != nullptr && std::strcmp(cap, "avx2") == 0;
  if (cap != nullptr && std::strcmp(cap, "default") == 0) return Isa::kNone;
  if (!capped_avx2 && __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") &&
      __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("avx512dq") &&
      __builtin_cpu_supports("fma")) {
    return Isa::kAvx512;
  }
  if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma")) return Isa::kAvx2;
#endif
  return Isa::kNone;
}

Isa CpuIsa() {
  static const Isa isa = ChooseIsa();
  return isa;
}

bool Operand(const torch::Tensor& t, int64_t head_dim) {
  return t.defined() && t.dim() == 4 && t.is_cpu() && t.scalar_type() == torch::kFloat32 &&
         t.size(3) == head_dim && (t.stride(3) == 1 || t.size(3) == 1);
}

}  // namespace

bool UseFusedAttention(const torch::Tensor& q, const torch::Tensor& k, const torch::Tensor& v) {
  if (!enabled.load(std::memory_order_relaxed) || CpuIsa() == Isa::kNone) return false;
  // Inference mode, not merely grad mode off: gradient checkpointing runs
  // its saving forward under no_grad and recomputes it with grad, and the two
  // must be the same arithmetic.
  if (!c10::InferenceMode::is_enabled() || !q.defined() || q.dim() != 4) return false;
  const int64_t d = q.size(3);
  if (d < 1 || d > kMaxFusedAttentionHeadDim) return false;
  if (!Operand(q, d) || !Operand(k, d) || !Operand(v, d)) return false;
  return k.size(0) == q.size(0) && v.size(0) == q.size(0) && k.size(1) == q.size(1) &&
         v.size(1) == q.size(1) && v.size(2) == k.size(2) && k.size(2) > 0;
}

torch::Tensor FusedAttention(const torch::Tensor& q, const torch::Tensor& k, const torch::Tensor& v,
                             double scale) {
  TORCH_CHECK(UseFusedAttention(q, k, v), "FusedAttention: operands it does not take");
  const int64_t b = q.size(0), h = q.size(1), lq = q.size(2), d = q.size(3);
  // [B, Lq, H, D] storage, returned as the [B, H, Lq, D] view.
  torch::Tensor out = torch::empty({b, lq, h, d}, q.options());
  attention_rows::Operands o;
  o.q = q.data_ptr<float>();
  o.k = k.data_ptr<float>();
  o.v = v.data_ptr<float>();
  o.out = out.data_ptr<float>();
  o.batch = b, o.heads = h, o.lq = lq, o.lk = k.size(2), o.head_dim = d;
  for (int i = 0; i < 3; ++i) {
    o.q_strides[i] = q.stride(i);
    o.k_strides[i] = k.stride(i);
    o.v_strides[i] = v.stride(i);
  }
  o.out_strides[0] = out.stride(0), o.out_strides[1] = out.stride(2);
  o.out_strides[2] = out.stride(1);
  o.scale = static_cast<float>(scale);
  const bool wide = CpuIsa() == Isa::kAvx512;
#if defined(FD_FUSED_ATTENTION_KERNELS)
  const attention_rows::AttendHeadsFn attend =
      wide ? attention_rows::AttendHeadsAvx512 : attention_rows::AttendHeadsAvx2;
#else
  const attention_rows::AttendHeadsFn attend = nullptr;  // UseFusedAttention said no
#endif
  const int64_t scratch_floats = attention_rows::ScratchFloats(
      o, wide ? attention_rows::kAvx512Width : attention_rows::kAvx2Width);
  at::parallel_for(0, b * h, /*grain_size=*/1, [&](int64_t begin, int64_t end) {
    std::vector<float> scratch(static_cast<size_t>(scratch_floats));
    attend(o, begin, end, scratch.data());
  });
  return out.transpose(1, 2);
}

void SetFusedAttentionEnabled(bool on) { enabled.store(on, std::memory_order_relaxed); }

std::string DescribeFusedAttention() {
  if (!enabled.load(std::memory_order_relaxed)) return "off: turned off";
  switch (CpuIsa()) {
    case Isa::kAvx512:
      return "avx512";
    case Isa::kAvx2:
      return "avx2";
    case Isa::kNone:
      break;
  }
#if defined(FD_FUSED_ATTENTION_KERNELS)
  return "off: no AVX2 + FMA (or ATEN_CPU_CAPABILITY=default)";
#else
  return "off: built without the kernels (FD_FUSED_CPU_ATTENTION off or not x86-64)";
#endif
}

}  // namespace fd::model
