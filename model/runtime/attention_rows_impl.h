// The fused attention loop, written once against ATen's Vectorized<float>
// and compiled per instruction set: attention_rows_avx2.cc and
// attention_rows_avx512.cc define FD_ATTENTION_ROWS_FN and ATen's
// CPU_CAPABILITY macros, then include this file. Include nowhere else.
//
// Vectorised across query rows, not keys: a vector holds the scores of W
// consecutive query rows (W = 8 or 16) against one key, so that with the
// small heads this kernel takes (D <= 16) nothing is reduced across lanes.
// Per (batch, head), q is transposed into [D, Lq] scratch rows; per block of
// W rows, pass 1 finds each row's maximum score s_j = (q . k_j) * scale over
// the keys, pass 2 recomputes s_j (D multiply-adds, cheaper than storing it)
// and accumulates l = sum_j exp(s_j - max) and acc_c = sum_j exp(s_j - max) *
// v_jc; out_c = acc_c / l. The same arithmetic as bmm -> softmax -> bmm up to
// float32 rounding (summation order), without writing the [Lq, Lk] score
// matrix to memory. Each row's result depends on its own q row, k and v only,
// whatever its lane (batch invariant).
//
// No standard-library templates here (std::min and the like): an
// out-of-line copy compiled with this file's -m flags could be the one the
// linker keeps for the whole program, and then run on a CPU without them.
#include <ATen/cpu/vec/vec.h>

#include <cstdint>

#include "model/runtime/attention_rows.h"

namespace fd::model::attention_rows {
namespace {

using Vec = at::vec::Vectorized<float>;

int64_t Padded(int64_t n) { return (n + Vec::size() - 1) / Vec::size() * Vec::size(); }

}  // namespace

void FD_ATTENTION_ROWS_FN(const Operands& o, int64_t begin, int64_t end, float* scratch) {
  constexpr int64_t kWidth = Vec::size();
  const int64_t lq = o.lq, lk = o.lk, d = o.head_dim, stride = Padded(lq);
  float* qt = scratch;  // [D, stride]
  const Vec scale(o.scale);
  const Vec zero(0.0f);
  for (int64_t bh = begin; bh < end; ++bh) {
    const int64_t b = bh / o.heads, h = bh % o.heads;
    const float* q = o.q + b * o.q_strides[0] + h * o.q_strides[1];
    const float* k = o.k + b * o.k_strides[0] + h * o.k_strides[1];
    const float* v = o.v + b * o.v_strides[0] + h * o.v_strides[1];
    float* out = o.out + b * o.out_strides[0] + h * o.out_strides[1];
    for (int64_t i = 0; i < stride; ++i) {
      for (int64_t c = 0; c < d; ++c)
        qt[c * stride + i] = i < lq ? q[i * o.q_strides[2] + c] : 0.0f;
    }
    for (int64_t i0 = 0; i0 < lq; i0 += kWidth) {
      Vec qv[kMaxHeadDim];
      for (int64_t c = 0; c < d; ++c) qv[c] = Vec::loadu(qt + c * stride + i0);
      auto score = [&](const float* key) {
        Vec s = zero;
        for (int64_t c = 0; c < d; ++c) s = at::vec::fmadd(qv[c], Vec(key[c]), s);
        return s * scale;
      };
      Vec m = score(k);
      for (int64_t j = 1; j < lk; ++j) m = at::vec::maximum(m, score(k + j * o.k_strides[2]));
      Vec l = zero;
      Vec acc[kMaxHeadDim];
      for (int64_t c = 0; c < d; ++c) acc[c] = zero;
      for (int64_t j = 0; j < lk; ++j) {
        const Vec e = (score(k + j * o.k_strides[2]) - m).exp();
        l = l + e;
        const float* value = v + j * o.v_strides[2];
        for (int64_t c = 0; c < d; ++c) acc[c] = at::vec::fmadd(e, Vec(value[c]), acc[c]);
      }
      const Vec inv = Vec(1.0f) / l;
      float lanes[kWidth];
      const int64_t rows = lq - i0 < kWidth ? lq - i0 : kWidth;
      for (int64_t c = 0; c < d; ++c) {
        (acc[c] * inv).store(lanes);
        for (int64_t r = 0; r < rows; ++r) out[(i0 + r) * o.out_strides[2] + c] = lanes[r];
      }
    }
  }
}

}  // namespace fd::model::attention_rows
