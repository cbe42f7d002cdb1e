// FusedAttention (model/runtime/attention_kernel.h): equal to ATen's
// bmm -> softmax -> bmm within float32 rounding for every head width it
// takes, at any query/key count (vector tails), with strided (head-split)
// operands; each instruction-set build on its own; batch invariance; the
// operands it refuses (outside inference mode, other dtypes, wide heads); and that the
// networks' attention uses it and stays equal to the unfused path.
#include "model/runtime/attention_kernel.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <cmath>

#include "model/networks/attention_processor.h"
#include "model/runtime/attention_rows.h"

namespace fd::model {
namespace {

// The unfused arithmetic (diffusers' get_attention_scores + bmm), in double.
torch::Tensor Reference(const torch::Tensor& q, const torch::Tensor& k, const torch::Tensor& v) {
  const double scale = 1.0 / std::sqrt(static_cast<double>(q.size(3)));
  const torch::Tensor scores =
      torch::matmul(q.to(torch::kFloat64), k.to(torch::kFloat64).transpose(-1, -2)) * scale;
  return torch::matmul(scores.softmax(-1), v.to(torch::kFloat64)).to(torch::kFloat32);
}

double MaxAbsDiff(const torch::Tensor& a, const torch::Tensor& b) {
  return (a - b).abs().max().item<double>();
}

// q, k, v as the attention processor makes them: [B, L, H*D] projections
// split into heads, i.e. [B, H, L, D] views with strides (L*H*D, D, H*D, 1).
struct Operands {
  torch::Tensor q, k, v;
};
Operands HeadSplit(int64_t batch, int64_t heads, int64_t lq, int64_t lk, int64_t d, uint64_t seed) {
  torch::manual_seed(seed);
  auto split = [&](int64_t l) {
    return (torch::randn({batch, l, heads * d}) * 2).view({batch, l, heads, d}).transpose(1, 2);
  };
  return {split(lq), split(lk), split(lk)};
}

struct Shape {
  int64_t batch, heads, lq, lk, d;
};

class FusedAttentionTest : public ::testing::TestWithParam<Shape> {};

TEST_P(FusedAttentionTest, EqualsTheUnfusedOpsWithinFloatRounding) {
  const Shape s = GetParam();
  const Operands o = HeadSplit(s.batch, s.heads, s.lq, s.lk, s.d, 7);
  torch::InferenceMode inference;
  if (DescribeFusedAttention().rfind("off", 0) == 0) {
    GTEST_SKIP() << "fused attention not available here: " << DescribeFusedAttention();
  }
  ASSERT_TRUE(UseFusedAttention(o.q, o.k, o.v));
  const torch::Tensor fused = FusedAttention(o.q, o.k, o.v, 1.0 / std::sqrt(double(s.d)));
  ASSERT_EQ(fused.sizes(), o.q.sizes());
  // Heads merge back without a copy: [B, Lq, H*D] is a view.
  EXPECT_TRUE(fused.transpose(1, 2).is_contiguous());
  // Against the double-precision reference, as close as the unfused float
  // ops are (both a few float32 roundings of the output's scale).
  const torch::Tensor reference = Reference(o.q, o.k, o.v);
  SetFusedAttentionEnabled(false);
  const torch::Tensor unfused = DotProductAttention(o.q, o.k, o.v, /*upcast_softmax=*/false);
  SetFusedAttentionEnabled(true);
  const double scale = reference.abs().max().item<double>();
  const double unfused_error = MaxAbsDiff(unfused, reference) / scale;
  EXPECT_LT(MaxAbsDiff(fused, reference) / scale, std::max(2 * unfused_error, 1e-6));
  EXPECT_LT(MaxAbsDiff(fused, unfused) / scale, 2e-6);
}

INSTANTIATE_TEST_SUITE_P(
    Shapes, FusedAttentionTest,
    ::testing::Values(Shape{1, 8, 192, 192, 2},   // config B level 0, self-attention
                      Shape{2, 8, 192, 77, 2},    // config B level 0, cross-attention
                      Shape{1, 8, 48, 48, 4},     // config B level 1
                      Shape{1, 8, 1024, 77, 4},   // street level 0, cross-attention
                      Shape{2, 3, 17, 33, 1},     // tails in both directions
                      Shape{1, 2, 5, 1, 8},       // one key
                      Shape{1, 1, 31, 100, 16}),  // the widest head it takes
    [](const ::testing::TestParamInfo<Shape>& info) {
      const Shape& s = info.param;
      return "b" + std::to_string(s.batch) + "h" + std::to_string(s.heads) + "q" +
             std::to_string(s.lq) + "k" + std::to_string(s.lk) + "d" + std::to_string(s.d);
    });

// Both instruction-set builds, called directly where the CPU runs them.
TEST(FusedAttentionRowsTest, EachInstructionSetBuildEqualsTheReference) {
#if !defined(FD_TEST_HAS_FUSED_ATTENTION)
  GTEST_SKIP() << "built without the fused attention kernels";
#else
  const Operands o = HeadSplit(2, 4, 37, 45, 4, 11);
  const torch::Tensor reference = Reference(o.q, o.k, o.v);
  __builtin_cpu_init();
  struct Build {
    const char* name;
    bool runs;
    attention_rows::AttendHeadsFn fn;
    int64_t width;
  };
  const Build builds[] = {
      {"avx2", __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"),
       attention_rows::AttendHeadsAvx2, attention_rows::kAvx2Width},
      {"avx512",
       __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") &&
           __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("avx512dq"),
       attention_rows::AttendHeadsAvx512, attention_rows::kAvx512Width},
  };
  int ran = 0;
  for (const Build& build : builds) {
    if (!build.runs) continue;
    ++ran;
    torch::Tensor out = torch::full({2, 37, 4, 4}, NAN);  // [B, Lq, H, D]
    attention_rows::Operands ops;
    ops.q = o.q.data_ptr<float>(), ops.k = o.k.data_ptr<float>(), ops.v = o.v.data_ptr<float>();
    ops.out = out.data_ptr<float>();
    ops.batch = 2, ops.heads = 4, ops.lq = 37, ops.lk = 45, ops.head_dim = 4;
    for (int i = 0; i < 3; ++i) {
      ops.q_strides[i] = o.q.stride(i), ops.k_strides[i] = o.k.stride(i);
      ops.v_strides[i] = o.v.stride(i);
    }
    ops.out_strides[0] = out.stride(0), ops.out_strides[1] = out.stride(2);
    ops.out_strides[2] = out.stride(1);
    ops.scale = 0.5f;  // 1 / sqrt(4)
    std::vector<float> scratch(
        static_cast<size_t>(attention_rows::ScratchFloats(ops, build.width)));
    build.fn(ops, 0, 8, scratch.data());
    EXPECT_LT(MaxAbsDiff(out.transpose(1, 2), reference), 1e-5) << build.name;
  }
  if (ran == 0) GTEST_SKIP() << "this CPU has neither AVX2 + FMA nor AVX-512";
#endif
}

TEST(FusedAttentionTest, RowsDoNotDependOnTheBatchOrTheThreads) {
  const Operands o = HeadSplit(3, 8, 50, 77, 2, 5);
  torch::InferenceMode inference;
  if (!UseFusedAttention(o.q, o.k, o.v)) GTEST_SKIP() << DescribeFusedAttention();
  const int threads = at::get_num_threads();
  at::set_num_threads(1);
  const torch::Tensor all = FusedAttention(o.q, o.k, o.v, 0.7);
  at::set_num_threads(2);
  const torch::Tensor all2 = FusedAttention(o.q, o.k, o.v, 0.7);
  at::set_num_threads(threads);
  EXPECT_TRUE(all.equal(all2));
  for (int64_t b = 0; b < 3; ++b) {
    const torch::Tensor one =
        FusedAttention(o.q.slice(0, b, b + 1), o.k.slice(0, b, b + 1), o.v.slice(0, b, b + 1), 0.7);
    EXPECT_TRUE(one.equal(all.slice(0, b, b + 1))) << "item " << b;
  }
}

TEST(FusedAttentionTest, RefusesWhatItDoesNotTake) {
  const Operands o = HeadSplit(1, 2, 8, 8, 4, 3);
  {
    torch::InferenceMode inference;
    if (!UseFusedAttention(o.q, o.k, o.v)) GTEST_SKIP() << DescribeFusedAttention();
    // Heads wider than the loop's registers, other dtypes, a mismatched v.
    const Operands wide = HeadSplit(1, 2, 8, 8, kMaxFusedAttentionHeadDim + 1, 3);
    EXPECT_FALSE(UseFusedAttention(wide.q, wide.k, wide.v));
    EXPECT_FALSE(UseFusedAttention(o.q.to(torch::kFloat64), o.k.to(torch::kFloat64),
                                   o.v.to(torch::kFloat64)));
    EXPECT_FALSE(UseFusedAttention(o.q, o.k, o.v.slice(2, 0, 4)));
    EXPECT_FALSE(UseFusedAttention(o.q.contiguous().transpose(2, 3), o.k, o.v));
    EXPECT_THROW(FusedAttention(wide.q, wide.k, wide.v, 1.0), c10::Error);
    SetFusedAttentionEnabled(false);
    EXPECT_FALSE(UseFusedAttention(o.q, o.k, o.v));
    EXPECT_EQ(DescribeFusedAttention(), "off: turned off");
    SetFusedAttentionEnabled(true);
  }
  // Training keeps ATen's differentiable ops, and so does a no_grad forward
  // outside inference mode (gradient checkpointing recomputes it with grad).
  EXPECT_FALSE(UseFusedAttention(o.q, o.k, o.v));
  torch::NoGradGuard no_grad;
  EXPECT_FALSE(UseFusedAttention(o.q, o.k, o.v));
}

// Through an attention layer as the networks run it (heads of 2, as config
// B's first level): the fused path equals the unfused one within rounding.
TEST(FusedAttentionTest, AttentionLayerMatchesTheUnfusedPath) {
  torch::manual_seed(9);
  AttentionOptions self_options;
  self_options.query_dim = 16;
  self_options.heads = 8;
  self_options.dim_head = 2;
  AttentionOptions cross_options = self_options;
  cross_options.cross_attention_dim = 40;
  Attention self_attention(self_options);
  Attention cross_attention(cross_options);
  const torch::Tensor x = torch::randn({2, 192, 16});
  const torch::Tensor context = torch::randn({2, 77, 40});
  torch::InferenceMode inference;
  SetFusedAttentionEnabled(false);
  const torch::Tensor unfused_self = self_attention->forward(x);
  const torch::Tensor unfused_cross = cross_attention->forward(x, context);
  SetFusedAttentionEnabled(true);
  EXPECT_LT(MaxAbsDiff(self_attention->forward(x), unfused_self), 1e-5);
  EXPECT_LT(MaxAbsDiff(cross_attention->forward(x, context), unfused_cross), 1e-5);
}

}  // namespace
}  // namespace fd::model
