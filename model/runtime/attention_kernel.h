// Fused scaled dot-product attention on the CPU for small heads.
//
// LibTorch 1.13 has no fused attention: the port computes bmm(q, k^T) * scale,
// softmax and bmm(p, v) (diffusers' AttnProcessor), writing and re-reading
// the [B*H, Lq, Lk] score matrix. With the small heads of the project's
// environments (head dimension 2-8: config B's 16-32 channels and street's
// 32-64 over 8 heads) the matrix multiplications are trivial and those passes,
// the softmax's exp and the ops' dispatch are the attention's whole cost: 39 %
// of a config-B frame (perf, 2026-12-05). FusedAttention computes each score in
// registers, twice (for the row maximum, then for the exp and the weighted
// sum of v), never storing the matrix, with ATen's own vectorised Sleef exp,
// per instruction set (AVX2 or AVX-512, chosen from the CPU at run time). Measured in
// docs/BENCHMARKS.md, "Fused attention".
#ifndef FD_MODEL_RUNTIME_ATTENTION_KERNEL_H_
#define FD_MODEL_RUNTIME_ATTENTION_KERNEL_H_

#include <torch/types.h>

#include <cstdint>
#include <string>

namespace fd::model {

// Heads wider than this take the ATen path: there the matrix multiplications
// are real work and BLAS does them better than the row loop.
inline constexpr int64_t kMaxFusedAttentionHeadDim = 16;  // = attention_rows::kMaxHeadDim

// Whether FusedAttention takes q [B, H, Lq, D], k and v [B, H, Lk, D]: built
// with the kernels (FD_FUSED_ATTENTION_KERNELS), enabled, a CPU with AVX2 and
// FMA (ATEN_CPU_CAPABILITY=default turns it off, =avx2 keeps it to AVX2),
// float32 CPU tensors with the last dimension contiguous, D <=
// kMaxFusedAttentionHeadDim, under torch::InferenceMode (as FramePipeline
// runs; training, and gradient checkpointing's no_grad forward, keep ATen's
// ops). Thread-safe.
bool UseFusedAttention(const torch::Tensor& q, const torch::Tensor& k, const torch::Tensor& v);

// softmax(q k^T * scale) v for operands UseFusedAttention accepts, as
// [B, H, Lq, D]: a view of a contiguous [B, Lq, H, D] tensor, so that merging
// the heads back ([B, Lq, H*D]) needs no copy. Equal to the ATen ops within
// float32 rounding. Rows run in parallel over the (batch, head) pairs on
// LibTorch's intra-op threads; every row's arithmetic is the same at any
// batch size or thread count (batch invariant). Throws c10::Error on
// operands UseFusedAttention refuses. Thread-safe.
torch::Tensor FusedAttention(const torch::Tensor& q, const torch::Tensor& k, const torch::Tensor& v,
                             double scale);

// Turns the fused kernel on or off for the process (default on), for
// benchmarks and tests that compare both paths. Thread-safe.
void SetFusedAttentionEnabled(bool enabled);

// "avx512", "avx2" or "off: <why>", for benchmark contexts and startup logs.
std::string DescribeFusedAttention();

}  // namespace fd::model

#endif  // FD_MODEL_RUNTIME_ATTENTION_KERNEL_H_
