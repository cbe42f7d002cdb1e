// The autoregressive state of one session: what frame t needs from frame t-1.
//
// Stored at the precision the reference pipeline itself uses (the authors'
// pipeline.py / inference.py): every output frame is quantised to uint8, the
// next frame's irradiance is computed from that uint8 frame and the previous
// uint8 basecolor, and the VAE re-encodes the uint8 previous frame every frame
// (its latent is sampled, not kept). So the state is
//   - the previous output frame,  uint8 HWC RGB  (W*H*3 bytes),
//   - the previous basecolor,     uint8 HWC RGB  (W*H*3 bytes),
//   - the frame counter (which seeds frame k's noise: frame_seed.h),
//   - the last client frame_index, the settings and the start mode.
// No irradiance map or live RNG is stored: all derive from the above,
// exactly as the reference derives them. At 512x512 that is 2 x 786,432 B =
// 1.5 MiB plus ~100 B, under the 2 MB budget of an idle session
// (MemoryBytes() reports the actual figure).
//
// The one exception is an environment whose environment.json says
// "previous_latent": "reuse" (a serving speed-up, not the reference's
// arithmetic): the last frame's denoised latent is kept too (float32
// C x H/f x W/f: 64 KiB at 512x512) and stands in for the VAE encode of the
// previous frame. It is not part of an exported state (state_blob.h): an
// imported session, a keyframe start, a re-seed and the first frame after a
// reload of the environment (a latent is taken only by the batcher that made
// it) encode their previous frame once, as the reference does, and keep
// latents from then on.
//
// The pipeline reads this state to build frame t's conditioning and, once the
// frame rendered, calls CommitFrame with its uint8 output; nothing here needs
// LibTorch. The images are shared, immutable buffers (base/image_buffer.h):
// the output kept here is the same buffer the stream encodes for the client. A mid-session re-seed
// (camera cut) is not stored here: it belongs to the one frame that carries the keyframe
// (Session::TryBeginFrame), and that frame's output replaces it on commit, so a failed re-seeded
// frame leaves the state untouched.
#ifndef FD_SESSION_SESSION_STATE_H_
#define FD_SESSION_SESSION_STATE_H_

#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "base/image_buffer.h"
#include "session/session_settings.h"

namespace fd::session {

// A frame's denoised latent (model::FrameOutput::latent without its batch
// dimension): float32, channels x height x width, row-major. Value type;
// copies share the immutable values.
struct LatentBuffer {
  uint32_t channels = 0;
  uint32_t height = 0;
  uint32_t width = 0;
  std::shared_ptr<const std::vector<float>> values;  // channels*height*width
  // Which loaded model made it (FrameBatcher::latent_source()): a latent is
  // only meaningful in the latent space of the autoencoder that made it, so
  // a batcher takes only its own (after a reload, the frame is encoded).
  uint64_t source = 0;

  bool empty() const { return values == nullptr; }
  size_t size_bytes() const { return empty() ? 0 : values->size() * sizeof(float); }
  // Equal shape and values (or both empty).
  friend bool operator==(const LatentBuffer& a, const LatentBuffer& b);
};

// Ownership: a value type; copies share the (immutable) pixel buffers.
// Thread-safety: none; the owner (Session) serialises access.
class SessionState {
 public:
  // A session that starts from a client keyframe: an RGB uint8 HWC image of
  // the session's size used as the "previous frame" of the first frame.
  // `keyframe_basecolor` is the basecolor of the frame the keyframe shows;
  // empty means "the first frame's own basecolor" (the wire API's default).
  // INVALID_ARGUMENT naming the field for invalid settings or sizes.
  static absl::StatusOr<SessionState> StartFromKeyframe(SessionSettings settings,
                                                        ImageBuffer keyframe,
                                                        ImageBuffer keyframe_basecolor);

  // A session that starts from the G-buffer only: until the first output
  // exists, frames are conditioned on black irradiance and a zero previous
  // latent. INVALID_ARGUMENT for invalid settings.
  static absl::StatusOr<SessionState> StartFromGBufferOnly(SessionSettings settings);

  // Rebuilds a state from its fields (ImportState uses it). Checks every
  // invariant the other constructors guarantee: valid settings, buffer
  // sizes, a previous frame whenever a keyframe started the session or a
  // frame was rendered, a basecolor only with a previous frame, and a last
  // frame index exactly when frames were rendered. INVALID_ARGUMENT naming
  // the field otherwise.
  static absl::StatusOr<SessionState> Restore(SessionSettings settings, StartMode start_mode,
                                              uint64_t frame_counter,
                                              std::optional<uint64_t> last_frame_index,
                                              ImageBuffer previous_frame,
                                              ImageBuffer previous_basecolor);

  // Records a rendered frame: `output` (uint8 HWC RGB, the frame sent to the
  // client) and `basecolor` (its uint8 HWC RGB basecolor as the client sent
  // it, NOT sky filled: the authors' irradiance of the next frame divides by
  // the raw previous basecolor) become the previous frame and
  // basecolor; the frame counter advances; `frame_index` becomes the last
  // frame index; `latent` (empty unless the environment reuses latents)
  // replaces the previous latent. INVALID_ARGUMENT on a size mismatch or a
  // latent whose values do not match its shape, FAILED_PRECONDITION if
  // frame_index is not greater than the last one; the state is then
  // unchanged.
  absl::Status CommitFrame(uint64_t frame_index, ImageBuffer output, ImageBuffer basecolor,
                           LatentBuffer latent = {});

  const SessionSettings& settings() const { return settings_; }
  StartMode start_mode() const { return start_mode_; }

  // Frames rendered so far; frame number frame_counter() (0-based) is next
  // and draws its noise from NextFrameSeed().
  uint64_t frame_counter() const { return frame_counter_; }
  uint64_t NextFrameSeed() const;
  // The client's frame_index of the last rendered frame, if any.
  const std::optional<uint64_t>& last_frame_index() const { return last_frame_index_; }

  // The next frame's "previous frame": the last output or a keyframe. False
  // only for a G-buffer-only session before its first frame (black
  // irradiance, zero previous latent).
  bool has_previous_frame() const { return !previous_frame_.empty(); }
  // False when the next frame's irradiance must use its own basecolor
  // (keyframe given without a basecolor), or when there is no previous frame.
  bool has_previous_basecolor() const { return !previous_basecolor_.empty(); }
  // uint8 HWC RGB of the session's size, or empty (see above).
  const ImageBuffer& previous_frame() const { return previous_frame_; }
  const ImageBuffer& previous_basecolor() const { return previous_basecolor_; }
  // The previous output's denoised latent; empty unless that output was
  // committed with one (see the header comment).
  const LatentBuffer& previous_latent() const { return previous_latent_; }

  // Bytes of one uint8 RGB image of this session: width*height*3.
  size_t ImageBytes() const;
  // INVALID_ARGUMENT "<field>: expected N bytes (W x H x 3 uint8), got M"
  // unless `pixels` is a W x H x 3 uint8 image (or is empty and
  // `allow_empty`).
  absl::Status CheckImage(const char* field, const ImageBuffer& pixels, bool allow_empty) const;
  // Memory this object holds: sizeof(*this) plus its pixel and latent buffers and the
  // heap capacity of its strings (a buffer shared with a frame being sent is
  // counted here too).
  size_t MemoryBytes() const;

  // Deep equality of every field (used by tests and export/import checks).
  friend bool operator==(const SessionState& a, const SessionState& b);
  friend bool operator!=(const SessionState& a, const SessionState& b) { return !(a == b); }

 private:
  SessionState() = default;

  SessionSettings settings_;
  StartMode start_mode_ = StartMode::kGBufferOnly;
  uint64_t frame_counter_ = 0;
  std::optional<uint64_t> last_frame_index_;
  ImageBuffer previous_frame_;
  ImageBuffer previous_basecolor_;
  LatentBuffer previous_latent_;
};

}  // namespace fd::session

#endif  // FD_SESSION_SESSION_STATE_H_
