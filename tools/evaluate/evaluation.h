// The paper's evaluation on rendered sequences (framediffuser-evaluate):
// the autoencoder round trip of the ground truth (the ceiling of any latent
// model), and per-frame PSNR / SSIM of rendered variants against the ground
// truth and against that round trip, frame-to-frame flicker, the temporal
// stability plot and a contact sheet (GT | ours | basecolor | irradiance).
// scripts/evaluate.sh renders the variants through a live server and calls
// this; docs/EVALUATION.md shows the results.
#ifndef FD_TOOLS_EVALUATE_EVALUATION_H_
#define FD_TOOLS_EVALUATE_EVALUATION_H_

#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace fd::evaluate {

// Decodes the VAE's posterior mean of every FinalImage frame of `sequence`
// (vae.decode(vae.encode(x).latent_dist.mean), the pipeline's uint8
// conversion) with the VAE of environment folder `env_dir` and writes
// <out_dir>/RoundTrip_<frame>.png. Returns the frame count.
// Errors: NOT_FOUND / INVALID_ARGUMENT from the VAE or the images, INTERNAL.
absl::StatusOr<int64_t> WriteRoundTrip(const std::string& env_dir, const std::string& sequence,
                                       const std::string& out_dir, int threads);

// Per latent channel of the VAE posterior over up to `frames` FinalImage
// frames of `sequence` (evenly spaced): the spread of the posterior mean
// across pixels and frames, and the mean posterior std. A channel whose
// mean barely varies and whose std is near 1 carries no information (the
// KL term made it noise); how many channels carry signal guides the choice
// of latent width. One text line per channel.
absl::StatusOr<std::string> DescribeLatents(const std::string& env_dir, const std::string& sequence,
                                            int frames);

struct Variant {
  std::string name;  // e.g. "FrameDiffuser (all stages)"
  std::string dir;   // rendered frames (framediffuser-client render --output)
};

struct ReportOptions {
  std::string sequence;           // ground truth: <sequence>/FinalImage, BaseColor
  std::string roundtrip;          // WriteRoundTrip's folder; empty: not reported
  std::vector<Variant> variants;  // the first is "ours" (plot, contact sheet)
  std::string out_dir;
  int contact_rows = 6;  // frames in the contact sheet, evenly spaced
  int window = 100;      // frames averaged for the first/last comparison
};

// Per variant: mean PSNR / SSIM against GT and round trip, first / last
// `window` frames, flicker. Writes <out_dir>/metrics.json (everything,
// per frame), per_frame.csv, results.md (tables), stability.png and
// contact_sheet.png. Frames are those every variant rendered.
// Errors: INVALID_ARGUMENT (no common frames, size mismatch), NOT_FOUND,
// INTERNAL (I/O).
absl::Status WriteReport(const ReportOptions& options);

}  // namespace fd::evaluate

#endif  // FD_TOOLS_EVALUATE_EVALUATION_H_
