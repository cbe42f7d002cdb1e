// Port of diffusers v0.31.0 Attention + AttnProcessor / AttnProcessor2_0
// (src/diffusers/models/attention_processor.py); see attention_processor.h.
#include "model/networks/attention_processor.h"

#include <torch/torch.h>
#include <torch/version.h>

#include <cmath>
#include <utility>
#include <vector>

#include "model/networks/prompt_kv_cache.h"
#include "model/runtime/attention_kernel.h"

namespace fd::model {

torch::Tensor DotProductAttention(const torch::Tensor& q, const torch::Tensor& k,
                                  const torch::Tensor& v, bool upcast_softmax) {
  // q: [B, H, Lq, D], k/v: [B, H, Lk, D]
#if TORCH_VERSION_MAJOR >= 2
  (void)upcast_softmax;  // AttnProcessor2_0 does not upcast either.
  return at::scaled_dot_product_attention(q, k, v);
#else
  const int64_t b = q.size(0), h = q.size(1), lq = q.size(2), d = q.size(3), lk = k.size(2);
  const double scale = 1.0 / std::sqrt(static_cast<double>(d));
  // Small float32 heads at inference: one fused pass per query row
  // (runtime/attention_kernel.h); upcasting is moot in float32.
  if (UseFusedAttention(q, k, v)) return FusedAttention(q, k, v, scale);
  torch::Tensor q3 = q.reshape({b * h, lq, d});
  torch::Tensor k3 = k.reshape({b * h, lk, d});
  torch::Tensor v3 = v.reshape({b * h, lk, d});
  // get_attention_scores: baddbmm(empty, q, k^T, beta=0, alpha=scale).
  torch::Tensor scores = torch::bmm(q3, k3.transpose(1, 2)).mul_(scale);  // [BH, Lq, Lk]
  torch::Tensor probs = upcast_softmax ? scores.to(torch::kFloat32).softmax(-1).to(q.scalar_type())
                                       : scores.softmax(-1);
  return torch::bmm(probs, v3).view({b, h, lq, d});  // [B, H, Lq, D]
#endif
}

AttentionImpl::AttentionImpl(const AttentionOptions& o) : options_(o) {
  namespace nn = torch::nn;
  const int64_t inner_dim = o.heads * o.dim_head;
  const int64_t cross_dim = o.cross_attention_dim > 0 ? o.cross_attention_dim : o.query_dim;
  if (o.norm_num_groups > 0) {
    group_norm = register_module(
        "group_norm",
        nn::GroupNorm(nn::GroupNormOptions(o.norm_num_groups, o.query_dim).eps(o.eps)));
  }
  to_q = register_module("to_q", LoraLinear(o.query_dim, inner_dim, o.bias));
  to_k = register_module("to_k", LoraLinear(cross_dim, inner_dim, o.bias));
  to_v = register_module("to_v", LoraLinear(cross_dim, inner_dim, o.bias));
  to_out_0_ = LoraLinear(inner_dim, o.query_dim, o.out_bias);
  to_out = register_module("to_out", nn::ModuleList(to_out_0_, nn::Dropout(0.0)));
}

torch::Tensor AttentionImpl::forward(const torch::Tensor& hidden_states,
                                     const torch::Tensor& encoder_hidden_states) {
  const torch::Tensor& residual = hidden_states;
  torch::Tensor x = hidden_states;
  const bool spatial = x.dim() == 4;
  int64_t channels = 0, height = 0, width = 0;
  if (spatial) {
    // [B, C, H, W] -> [B, H*W, C]
    channels = x.size(1), height = x.size(2), width = x.size(3);
    x = x.view({x.size(0), channels, height * width}).transpose(1, 2);
  }
  const int64_t batch = x.size(0);
  if (group_norm) x = group_norm(x.transpose(1, 2)).transpose(1, 2);

  const torch::Tensor& context = encoder_hidden_states.defined() ? encoder_hidden_states : x;
  const int64_t heads = options_.heads;
  // [B, L, H*D] -> [B, H, L, D]
  auto split_heads = [&](const torch::Tensor& t) {
    return t.view({batch, t.size(1), heads, t.size(2) / heads}).transpose(1, 2);
  };
  torch::Tensor q = split_heads(to_q(x));
  torch::Tensor k, v;
  const PromptKvScope* scope = encoder_hidden_states.defined() ? PromptKvScope::Current() : nullptr;
  if (scope != nullptr && static_cast<int64_t>(scope->rows().size()) == batch &&
      scope->rows().front().size(1) == context.size(1)) {
    // Prompt K/V that do not change between steps (prompt_kv_cache.h): each
    // item's, projected alone, then concatenated like the prompts.
    std::vector<torch::Tensor> keys, values;
    for (const torch::Tensor& row : scope->rows()) {
      PromptKvCache::KeyValue kv = scope->cache()->Get(this, row, [&] {
        const torch::Tensor prompt = row.to(context.options());  // as the networks' Run casts it
        return PromptKvCache::KeyValue(to_k(prompt), to_v(prompt));
      });
      keys.push_back(std::move(kv.first));
      values.push_back(std::move(kv.second));
    }
    k = split_heads(keys.size() == 1 ? keys.front() : torch::cat(keys, 0));
    v = split_heads(values.size() == 1 ? values.front() : torch::cat(values, 0));
  } else {
    k = split_heads(to_k(context));
    v = split_heads(to_v(context));
  }
  const torch::ScalarType dtype = q.scalar_type();
  if (options_.upcast_attention) {
    q = q.to(torch::kFloat32);
    k = k.to(torch::kFloat32);
  }
  torch::Tensor out = DotProductAttention(q, k, v.to(q.scalar_type()), options_.upcast_softmax);
  // [B, H, Lq, D] -> [B, Lq, H*D]
  out = out.to(dtype).transpose(1, 2).reshape({batch, out.size(2), out.size(1) * out.size(3)});
  out = to_out_0_(out);  // [B, Lq, query_dim]; to_out[1] is dropout (identity)

  if (spatial) out = out.transpose(-1, -2).reshape({batch, channels, height, width});
  if (options_.residual_connection) out = out + residual;
  if (options_.rescale_output_factor != 1.0) out = out / options_.rescale_output_factor;
  return out;
}

}  // namespace fd::model
