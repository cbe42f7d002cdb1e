// Batch-invariant execution of the networks' convolutions and linear layers.
//
// A frame batched with other sessions' frames should come out exactly as it
// does alone. LibTorch's CPU kernels choose their blocking by batch size:
// oneDNN picks another convolution kernel for a minibatch of 2 than of 1, and
// OpenBLAS computes a row of a GEMM with another micro-kernel when the number
// of rows changes. A sample's result then moves by float32 noise (~1e-6)
// with the batch it shares. Within one frame that is harmless, but the output
// is rounded to uint8 and becomes the next frame's input, so a value that sits
// on a rounding boundary can flip by 1/255 and the session's later frames
// drift from its solo run (tests/session/frame_batcher_test.cc).
//
// While a BatchInvariantScope is active on a thread, LoraConv2d and LoraLinear
// (every convolution and linear layer of the UNet, ControlNet and VAE) run each
// sample of their batch as its own batch-1 call, so each sample's result is
// bitwise the result it has alone. The other ops are per-sample already
// (GroupNorm, LayerNorm, softmax and batched matmuls compute each sample by
// itself; elementwise ops do not mix samples). What batching still saves is
// the per-call framework overhead of everything but the convolutions and
// linears; the cost is measured in docs/BENCHMARKS.md ("Batch invariance").
#ifndef FD_MODEL_RUNTIME_BATCH_INVARIANCE_H_
#define FD_MODEL_RUNTIME_BATCH_INVARIANCE_H_

namespace fd::model {

// RAII: enables (or, with `enabled` false, leaves unchanged) batch-invariant
// execution on the calling thread until destroyed; scopes nest. Like
// torch::InferenceMode, it is thread-local: create it on the thread that runs
// the forward. Thread-safety: each object belongs to the thread that made it.
class BatchInvariantScope {
 public:
  explicit BatchInvariantScope(bool enabled = true);
  ~BatchInvariantScope();
  BatchInvariantScope(const BatchInvariantScope&) = delete;
  BatchInvariantScope& operator=(const BatchInvariantScope&) = delete;

  // Whether batch-invariant execution is on for the calling thread.
  static bool Active();

 private:
  bool previous_;
};

}  // namespace fd::model

#endif  // FD_MODEL_RUNTIME_BATCH_INVARIANCE_H_
