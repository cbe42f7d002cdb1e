// CLIPTextModel, ported from transformers v4.30
// src/transformers/models/clip/modeling_clip.py (CLIPTextEmbeddings,
// CLIPAttention, CLIPMLP, CLIPEncoderLayer, CLIPEncoder,
// CLIPTextTransformer, CLIPTextModel): the SD1.5 text encoder.
//
// Modules are registered under the transformers state-dict names
// (text_model.embeddings.token_embedding.weight,
// text_model.encoder.layers.N.self_attn.q_proj.weight, ...), so
// named_parameters() + named_buffers() equal CLIPTextModel.state_dict() of
// transformers 4.30, including the `text_model.embeddings.position_ids`
// buffer that SD1.5 checkpoints carry (newer exports lack it; the loader
// accepts both).
#ifndef FD_MODEL_TEXT_CLIP_TEXT_MODEL_H_
#define FD_MODEL_TEXT_CLIP_TEXT_MODEL_H_

#include <torch/nn/module.h>
#include <torch/nn/modules/container/modulelist.h>
#include <torch/nn/modules/embedding.h>
#include <torch/nn/modules/linear.h>
#include <torch/nn/modules/normalization.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "model/checkpoint/file_source.h"
#include "model/networks/debug_taps.h"
#include "model/networks/model_configs.h"
#include "model/text/clip_tokenizer.h"

namespace fd::model {

// CLIPAttention: multi-head self-attention with the causal mask (no padding
// mask: SD1.5 passes none).
class ClipAttentionImpl : public torch::nn::Module {
 public:
  explicit ClipAttentionImpl(const CLIPTextConfig& config);
  // x: [N, L, H]; causal_mask: [L, L] (0 on/below the diagonal, the dtype's
  // lowest value above) -> [N, L, H]
  torch::Tensor forward(const torch::Tensor& x, const torch::Tensor& causal_mask,
                        DebugTaps* taps = nullptr, const std::string& prefix = "");

  torch::nn::Linear k_proj{nullptr};
  torch::nn::Linear v_proj{nullptr};
  torch::nn::Linear q_proj{nullptr};
  torch::nn::Linear out_proj{nullptr};

 private:
  int64_t num_heads_;
  int64_t head_dim_;
  double scale_;
};
TORCH_MODULE(ClipAttention);

// CLIPMLP: fc2(act(fc1(x))), act = quick_gelu (x * sigmoid(1.702 x)) or gelu.
class ClipMlpImpl : public torch::nn::Module {
 public:
  explicit ClipMlpImpl(const CLIPTextConfig& config);
  // x: [N, L, H] -> [N, L, H]
  torch::Tensor forward(const torch::Tensor& x, DebugTaps* taps = nullptr,
                        const std::string& prefix = "");

  torch::nn::Linear fc1{nullptr};
  torch::nn::Linear fc2{nullptr};

 private:
  bool quick_gelu_;
};
TORCH_MODULE(ClipMlp);

// CLIPEncoderLayer (pre-LN): x + attn(ln1(x)), then + mlp(ln2(.)).
class ClipEncoderLayerImpl : public torch::nn::Module {
 public:
  explicit ClipEncoderLayerImpl(const CLIPTextConfig& config);
  // x: [N, L, H] -> [N, L, H]
  torch::Tensor forward(const torch::Tensor& x, const torch::Tensor& causal_mask,
                        DebugTaps* taps = nullptr, const std::string& prefix = "");

  ClipAttention self_attn{nullptr};
  torch::nn::LayerNorm layer_norm1{nullptr};
  ClipMlp mlp{nullptr};
  torch::nn::LayerNorm layer_norm2{nullptr};
};
TORCH_MODULE(ClipEncoderLayer);

// CLIPTextEmbeddings: token_embedding[ids] + position_embedding[0..L-1].
class ClipTextEmbeddingsImpl : public torch::nn::Module {
 public:
  explicit ClipTextEmbeddingsImpl(const CLIPTextConfig& config);
  // input_ids: [N, L] int64 -> [N, L, H]
  torch::Tensor forward(const torch::Tensor& input_ids);

  torch::nn::Embedding token_embedding{nullptr};
  torch::nn::Embedding position_embedding{nullptr};
  torch::Tensor position_ids;  // int64 [1, max_position_embeddings] = 0..P-1
};
TORCH_MODULE(ClipTextEmbeddings);

// CLIPEncoder: the stack of layers (registered as "layers").
class ClipEncoderImpl : public torch::nn::Module {
 public:
  explicit ClipEncoderImpl(const CLIPTextConfig& config);
  torch::nn::ModuleList layers{nullptr};
  std::vector<ClipEncoderLayer> layer_list;
};
TORCH_MODULE(ClipEncoder);

struct ClipTextOutput {
  torch::Tensor last_hidden_state;           // [N, L, H]: final_layer_norm(encoder output)
  torch::Tensor pooler_output;               // [N, H]: last_hidden_state at the eos position
  std::vector<torch::Tensor> hidden_states;  // num_layers + 1 entries of [N, L, H]:
                                             // embeddings, then each layer's output
};

// CLIPTextTransformer (registered as "text_model").
class ClipTextTransformerImpl : public torch::nn::Module {
 public:
  explicit ClipTextTransformerImpl(const CLIPTextConfig& config);
  // input_ids: [N, L] int64, L <= max_position_embeddings.
  // taps: "encoder.layers.0.layer_norm1", ".self_attn.{q,k,v}_proj" (q before
  // scaling), ".self_attn", ".layer_norm2", ".mlp.fc1", ".mlp" for every layer.
  ClipTextOutput forward(const torch::Tensor& input_ids, DebugTaps* taps = nullptr);

  ClipTextEmbeddings embeddings{nullptr};
  ClipEncoder encoder{nullptr};
  torch::nn::LayerNorm final_layer_norm{nullptr};

 private:
  CLIPTextConfig config_;
};
TORCH_MODULE(ClipTextTransformer);

// Thread-safety: Run/forward may run concurrently (no state is mutated) as
// long as nobody changes the weights meanwhile.
class ClipTextModelImpl : public torch::nn::Module {
 public:
  explicit ClipTextModelImpl(const CLIPTextConfig& config);

  // The transformers forward, torch-style (throws on bad input).
  ClipTextOutput forward(const torch::Tensor& input_ids, DebugTaps* taps = nullptr);

  // Checked entry point: input_ids must be an integer tensor [N, L] with
  // 1 <= L <= max_position_embeddings and ids in [0, vocab_size); it is
  // moved to the model's device. Errors: INVALID_ARGUMENT naming input_ids,
  // INTERNAL for torch errors.
  absl::StatusOr<ClipTextOutput> Run(const torch::Tensor& input_ids, DebugTaps* taps = nullptr);

  // diffusers' encode_prompt: last_hidden_state when clip_skip == 0, else
  // final_layer_norm(hidden_states[-(clip_skip + 1)]). [N, L, H].
  // INVALID_ARGUMENT when clip_skip is negative or >= the number of layers.
  absl::StatusOr<torch::Tensor> PromptEmbeds(const torch::Tensor& input_ids, int clip_skip = 0);

  const CLIPTextConfig& config() const { return config_; }

  ClipTextTransformer text_model{nullptr};

 private:
  CLIPTextConfig config_;
};
TORCH_MODULE(ClipTextModel);

// Builds a CLIPTextModel with zero weights on the CPU in float32.
// INVALID_ARGUMENT for inconsistent sizes; UNIMPLEMENTED for an activation
// other than quick_gelu/gelu.
absl::StatusOr<ClipTextModel> MakeClipTextModel(const CLIPTextConfig& config);

// Loads `dir`/config.json and `dir`/model.safetensors (an SD1.5
// `text_encoder/` folder) strictly (the position_ids buffer may be absent),
// then moves the model to `device` / `dtype` in eval mode.
// Errors: NOT_FOUND (missing file), INVALID_ARGUMENT (bad config; missing,
// unexpected or mis-shaped weights, all listed), INTERNAL.
absl::StatusOr<ClipTextModel> LoadClipTextModel(const std::string& dir, torch::Device device,
                                                torch::Dtype dtype,
                                                const FileSource& files = DiskFiles());

// Prompt -> prompt_embeds as an SD1.5 pipeline computes them: tokenizer with
// padding to max length, then PromptEmbeds. [N, max_length, H] on the
// model's device. Errors as above.
absl::StatusOr<torch::Tensor> EncodePrompts(const ClipTokenizer& tokenizer, ClipTextModel& model,
                                            const std::vector<std::string>& prompts,
                                            int clip_skip = 0);

// A precomputed text embedding instead of a text encoder: the tensor
// `prompt_embeds` (or the file's only tensor) of a .safetensors file,
// floating point [N, L, H] or [L, H] (returned as [1, L, H]), finite.
// Errors: NOT_FOUND (no file), INVALID_ARGUMENT (no such tensor, wrong
// rank/dtype, NaN/Inf; naming the file).
absl::StatusOr<torch::Tensor> LoadPromptEmbeds(const std::string& path,
                                               const FileSource& files = DiskFiles());

}  // namespace fd::model

#endif  // FD_MODEL_TEXT_CLIP_TEXT_MODEL_H_
