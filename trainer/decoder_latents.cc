// Chains rendered for the decoder fine-tune; see decoder_latents.h.
#include "trainer/decoder_latents.h"

#include <torch/torch.h>

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "base/status_macros.h"
#include "client_sdk/metrics.h"
#include "model/pipeline/frame_pipeline.h"
#include "model/runtime/torch_call.h"
#include "trainer/sample_builder.h"
#include "trainer/validation.h"

namespace fd::trainer {
namespace {

// One chain: its sequence, keyframe and how far it has got.
struct Chain {
  int sequence = 0;
  int64_t keyframe = 0;
  int64_t length = 0;      // frames rendered after the keyframe
  torch::Tensor previous;  // uint8 [3, H, W]: the keyframe, then the last output
  torch::Tensor previous_latent;
};

// A stream of its own (sample_builder.h's MixSeed; the stage slots are 0-5).
constexpr uint64_t kStream = 0xDEC0DE;

}  // namespace

absl::StatusOr<DecoderLatentSet> RenderDecoderLatents(
    const std::shared_ptr<const fd::model::Environment>& environment, const TrainingData& data,
    const DecoderLatentOptions& options) {
  if (options.chains < 1 || options.chain_frames < 1) {
    return absl::InvalidArgumentError("decoder latents: chains and chain frames must be >= 1");
  }
  const fd::model::EnvironmentSettings& settings = environment->settings;
  if (settings.width != data.width || settings.height != data.height) {
    return absl::InvalidArgumentError(absl::StrCat(
        "--decoder_latents_from ", environment->dir, " serves ", settings.width, "x",
        settings.height, " frames; the training resolution is ", data.width, "x", data.height));
  }
  // Chains start where a following frame exists.
  std::vector<int64_t> starts_per_sequence;
  int64_t total = 0;
  for (const TrainingSequence& seq : data.sequences) {
    starts_per_sequence.push_back(std::max<int64_t>(0, seq.size() - 1));
    total += starts_per_sequence.back();
  }
  if (total == 0) {
    return absl::InvalidArgumentError("decoder latents: no training sequence has two frames");
  }
  return fd::model::TorchCall("decoder latents", [&]() -> absl::StatusOr<DecoderLatentSet> {
    SampleRandom rng(MixSeed(options.seed, kStream, 0));
    std::vector<Chain> chains;
    for (int c = 0; c < options.chains; ++c) {
      int64_t flat = static_cast<int64_t>(rng.engine() % static_cast<uint64_t>(total));
      size_t s = 0;
      while (flat >= starts_per_sequence[s]) flat -= starts_per_sequence[s++];
      const TrainingSequence& seq = data.sequences[s];
      // Room for a whole chain where the sequence has it.
      const int64_t last_start = std::max<int64_t>(0, seq.size() - 1 - options.chain_frames);
      const int64_t keyframe = flat % (last_start + 1);
      chains.push_back({static_cast<int>(s), keyframe,
                        std::min<int64_t>(options.chain_frames, seq.size() - 1 - keyframe),
                        seq.final_image[keyframe], torch::Tensor()});
    }

    fd::model::FramePipeline pipeline(environment);
    DecoderLatentSet out;
    double psnr_sum = 0;
    // Four chains per pipeline call, in lockstep (stage 3's generation batch).
    constexpr size_t kBatch = 4;
    for (size_t first = 0; first < chains.size(); first += kBatch) {
      const size_t end = std::min(chains.size(), first + kBatch);
      for (int64_t k = 1; k <= options.chain_frames; ++k) {
        std::vector<size_t> active;
        std::vector<fd::model::PipelineInput> requests;
        for (size_t i = first; i < end; ++i) {
          Chain& chain = chains[i];
          if (k > chain.length) continue;
          const TrainingSequence& seq = data.sequences[static_cast<size_t>(chain.sequence)];
          const int64_t position = chain.keyframe + k;
          fd::model::PipelineInput request =
              MakeFrameRequest({&seq, position, chain.previous, position - 1,
                                MixSeed(options.seed, kStream + 1 + i, static_cast<uint64_t>(k))});
          // As served (the sky filled from the frame's ground truth, as
          // scripts/evaluate.sh's client sends it), the previous latent as
          // the environment's "previous_latent" says (a keyframe is always
          // encoded).
          if (settings.reuse_previous_latent && chain.previous_latent.defined()) {
            request.prev_latent = chain.previous_latent;
          }
          requests.push_back(std::move(request));
          active.push_back(i);
        }
        if (requests.empty()) break;
        FD_ASSIGN_OR_RETURN(std::vector<fd::model::FrameOutput> outputs, pipeline.Render(requests));
        for (size_t j = 0; j < outputs.size(); ++j) {
          Chain& chain = chains[active[j]];
          const TrainingSequence& seq = data.sequences[static_cast<size_t>(chain.sequence)];
          const int64_t position = chain.keyframe + k;
          chain.previous = outputs[j].image_uint8.permute({2, 0, 1}).contiguous();
          chain.previous_latent = outputs[j].latent;
          FD_ASSIGN_OR_RETURN(
              const double psnr,
              fd::client::Psnr(ToImageF(outputs[j].image_uint8),
                               ToImageF(seq.final_image[position].permute({1, 2, 0}))));
          psnr_sum += psnr;
          out.latents.push_back({chain.sequence, position,
                                 outputs[j].latent.squeeze(0).to(torch::kCPU, torch::kFloat32)});
        }
      }
    }
    out.mean_psnr = psnr_sum / static_cast<double>(out.latents.size());
    return out;
  });
}

}  // namespace fd::trainer
