// framediffuser-evaluate: the paper's evaluation on rendered sequences
// (tools/evaluate/evaluation.h); scripts/evaluate.sh drives it.
#include <cstdio>
#include <string>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "model/runtime/cpu_runtime.h"
#include "tools/evaluate/denoising.h"
#include "tools/evaluate/evaluation.h"

namespace {

constexpr char kUsage[] =
    R"(usage: framediffuser-evaluate roundtrip --env DIR --input SEQ --out DIR [--threads N]
       framediffuser-evaluate latents --env DIR --input SEQ [--frames N]
       framediffuser-evaluate denoise --env DIR --input SEQ [--frames N]
                              [--timesteps T,T,...] [--out SHEET.png]
       framediffuser-evaluate report --input SEQ [--roundtrip DIR]
                              --variant NAME=DIR [--variant NAME=DIR ...] --out DIR
                              [--window N] [--contact_rows N]

roundtrip  the ground truth (SEQ/FinalImage) through the environment's VAE
           (posterior mean, decoded): the ceiling of any latent model.
latents    per channel of the VAE posterior over --frames N frames (default 6):
           spread of the mean and mean posterior std; a channel with std near
           1 and no spread is noise that the KL term made.
denoise    one-step denoising per timestep (default 100,300,500,700,900) on
           --frames N frames (default 6), teacher-forced: the ground truth
           noised to t, the noise predicted once from the frame's G-buffer
           and the ground-truth previous frame; the x0 estimate's PSNR
           against the round trip. --out: a sheet, per frame the round trip
           and the x0 estimate at each t.
report     per-frame PSNR / SSIM of each rendered variant against the ground
           truth and the round trip, first / last N frames (default 100),
           flicker; writes metrics.json, per_frame.csv, results.md,
           stability.png (the first variant) and contact_sheet.png
           (ground truth | first variant | basecolor | irradiance).

Exit status: 0 success, 1 failure, 2 bad command line.
)";

int Usage(const std::string& problem) {
  std::fprintf(stderr, "framediffuser-evaluate: %s\n%s", problem.c_str(), kUsage);
  return 2;
}

// A text-reporting command's result: the text on stdout (exit 0), or the
// error on stderr (exit 1).
int PrintText(const absl::StatusOr<std::string>& text) {
  if (!text.ok()) {
    std::fprintf(stderr, "framediffuser-evaluate: %s\n",
                 std::string(text.status().message()).c_str());
    return 1;
  }
  std::fputs(text->c_str(), stdout);
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  fd::model::UseBoundedOpenMpSpin(argv);
  std::vector<std::string> args(argv + 1, argv + argc);
  if (args.empty() || args[0] == "--help" || args[0] == "-h") {
    std::fputs(kUsage, args.empty() ? stderr : stdout);
    return args.empty() ? 2 : 0;
  }
  const std::string command = args[0];
  if (command != "roundtrip" && command != "report" && command != "latents" &&
      command != "denoise") {
    return Usage(absl::StrCat("unknown command '", command.substr(0, 64), "'"));
  }
  std::string env, input, out, roundtrip;
  int threads = 1, window = 100, rows = 6;  // rows: contact-sheet rows, or latents' frames
  std::vector<fd::evaluate::Variant> variants;
  std::vector<int> timesteps = fd::evaluate::DenoisingOptions().timesteps;
  for (size_t i = 1; i < args.size(); ++i) {
    const std::string& flag = args[i];
    if (i + 1 >= args.size()) return Usage(absl::StrCat(flag.substr(0, 64), " needs a value"));
    const std::string& value = args[++i];
    auto number = [&](int* target, int min) {
      return absl::SimpleAtoi(value, target) && *target >= min;
    };
    if (flag == "--env") {
      env = value;
    } else if (flag == "--input") {
      input = value;
    } else if (flag == "--out") {
      out = value;
    } else if (flag == "--roundtrip" && command == "report") {
      roundtrip = value;
    } else if (flag == "--variant" && command == "report") {
      const size_t eq = value.find('=');
      if (eq == std::string::npos || eq == 0 || eq + 1 == value.size()) {
        return Usage("--variant expects NAME=DIR");
      }
      variants.push_back({value.substr(0, eq), value.substr(eq + 1)});
    } else if (flag == "--timesteps" && command == "denoise") {
      timesteps.clear();
      for (absl::string_view part : absl::StrSplit(value, ',')) {
        int t = 0;
        if (!absl::SimpleAtoi(part, &t) || t < 0) {
          return Usage("--timesteps expects integers >= 0, comma separated");
        }
        timesteps.push_back(t);
      }
    } else if (flag == "--frames" && (command == "latents" || command == "denoise")) {
      if (!number(&rows, 1)) return Usage("--frames expects an integer >= 1");
    } else if (flag == "--threads" && command == "roundtrip") {
      if (!number(&threads, 1)) return Usage("--threads expects an integer >= 1");
    } else if (flag == "--window" && command == "report") {
      if (!number(&window, 1)) return Usage("--window expects an integer >= 1");
    } else if (flag == "--contact_rows" && command == "report") {
      if (!number(&rows, 1)) return Usage("--contact_rows expects an integer >= 1");
    } else {
      return Usage(absl::StrCat("unknown flag for ", command, ": ", flag.substr(0, 64)));
    }
  }
  if (input.empty()) return Usage("--input is required");
  if (out.empty() && command != "latents" && command != "denoise") {
    return Usage("--out is required");
  }
  if (command == "denoise") {
    if (env.empty()) return Usage("denoise needs --env");
    fd::evaluate::DenoisingOptions options;
    options.env_dir = env;
    options.sequence = input;
    options.frames = rows;
    options.timesteps = timesteps;
    options.sheet = out;
    return PrintText(fd::evaluate::DescribeDenoising(options));
  }
  if (command == "latents") {
    if (env.empty()) return Usage("latents needs --env");
    return PrintText(fd::evaluate::DescribeLatents(env, input, rows));
  }
  if (command == "roundtrip") {
    if (env.empty()) return Usage("roundtrip needs --env");
    fd::model::UseSingleThreadedBlas();
    absl::StatusOr<int64_t> frames = fd::evaluate::WriteRoundTrip(env, input, out, threads);
    if (!frames.ok()) {
      std::fprintf(stderr, "framediffuser-evaluate: %s\n",
                   std::string(frames.status().message()).c_str());
      return 1;
    }
    std::printf("framediffuser-evaluate: %lld round-trip frames in %s\n",
                static_cast<long long>(*frames), out.c_str());
    return 0;
  }
  if (variants.empty()) return Usage("report needs at least one --variant");
  fd::evaluate::ReportOptions options;
  options.sequence = input;
  options.roundtrip = roundtrip;
  options.variants = variants;
  options.out_dir = out;
  options.window = window;
  options.contact_rows = rows;
  if (absl::Status s = fd::evaluate::WriteReport(options); !s.ok()) {
    std::fprintf(stderr, "framediffuser-evaluate: %s\n", std::string(s.message()).c_str());
    return 1;
  }
  std::printf("framediffuser-evaluate: report in %s\n", out.c_str());
  return 0;
}
