// The plain-pointer interface between attention_kernel.cc (tensors, checks,
// threads) and the per-instruction-set builds of the fused attention loop
// (attention_rows_avx2.cc, attention_rows_avx512.cc). No LibTorch types here:
// the instruction-set builds include only ATen's vector header, compiled with
// their own -m flags.
#ifndef FD_MODEL_RUNTIME_ATTENTION_ROWS_H_
#define FD_MODEL_RUNTIME_ATTENTION_ROWS_H_

#include <cstdint>

namespace fd::model::attention_rows {

// One attention call's operands: q [B, H, Lq, D], k and v [B, H, Lk, D],
// out [B, H, Lq, D], each addressed by its (batch, head, row) strides in
// elements with the last dimension contiguous.
struct Operands {
  const float* q = nullptr;
  const float* k = nullptr;
  const float* v = nullptr;
  float* out = nullptr;
  int64_t batch = 0, heads = 0, lq = 0, lk = 0, head_dim = 0;
  int64_t q_strides[3] = {0, 0, 0};
  int64_t k_strides[3] = {0, 0, 0};
  int64_t v_strides[3] = {0, 0, 0};
  int64_t out_strides[3] = {0, 0, 0};
  float scale = 1.0f;
};

// The widest head the loop takes (its accumulators live in registers).
inline constexpr int64_t kMaxHeadDim = 16;

// Scratch floats that AttendHeads needs per call: q transposed for one head
// ([D, Lq], Lq padded to whole vectors of `vector_width` floats).
inline int64_t ScratchFloats(const Operands& o, int64_t vector_width) {
  const int64_t padded = (o.lq + vector_width - 1) / vector_width * vector_width;
  return o.head_dim * padded;
}

// softmax(q k^T * scale) v for the flattened (batch, head) pairs
// [begin, end), head_dim <= kMaxHeadDim, a block of query rows at a time:
// the scores never reach memory. `scratch` holds ScratchFloats(o, width) floats. Each
// instruction-set build defines its own; call only the one the CPU runs.
using AttendHeadsFn = void (*)(const Operands& o, int64_t begin, int64_t end, float* scratch);
void AttendHeadsAvx2(const Operands& o, int64_t begin, int64_t end, float* scratch);
void AttendHeadsAvx512(const Operands& o, int64_t begin, int64_t end, float* scratch);
inline constexpr int64_t kAvx2Width = 8;
inline constexpr int64_t kAvx512Width = 16;

}  // namespace fd::model::attention_rows

#endif  // FD_MODEL_RUNTIME_ATTENTION_ROWS_H_
