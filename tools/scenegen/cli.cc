#include "tools/scenegen/cli.h"

#include <cstdint>
#include <optional>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"
#include "tools/scenegen/scenes.h"

namespace fd::scenegen {
namespace {

absl::Status FlagError(const std::string& flag, const std::string& message) {
  return absl::InvalidArgumentError(absl::StrCat(flag, ": ", message));
}

absl::StatusOr<int> ParseIntFlag(const std::string& flag, const std::string& value, int lo,
                                 int hi) {
  int parsed = 0;
  if (!absl::SimpleAtoi(value, &parsed) || parsed < lo || parsed > hi) {
    return FlagError(
        flag, absl::StrCat("expected an integer in [", lo, ", ", hi, "], got '", value, "'"));
  }
  return parsed;
}

}  // namespace

absl::StatusOr<CliCommand> ParseCommandLine(const std::vector<std::string>& args) {
  CliCommand command;
  GeneratorOptions& o = command.options;
  bool have_out = false;
  bool help = false;
  bool list = false;
  for (size_t i = 0; i < args.size(); ++i) {
    const std::string& arg = args[i];
    if (arg == "--help" || arg == "-h") {
      help = true;
      continue;
    }
    if (arg == "--list-scenes") {
      list = true;
      continue;
    }
    if (!absl::StartsWith(arg, "--")) {
      return absl::InvalidArgumentError(
          absl::StrCat("unexpected argument '", arg, "' (flags start with --)"));
    }
    std::string flag = arg;
    std::optional<std::string> value;
    if (const size_t eq = arg.find('='); eq != std::string::npos) {
      flag = arg.substr(0, eq);
      value = arg.substr(eq + 1);
    }
    static const char* const kValueFlags[] = {"--scene", "--frames", "--start",  "--size",
                                              "--seed",  "--out",    "--format", "--threads"};
    bool known = false;
    for (const char* f : kValueFlags) known = known || flag == f;
    if (!known) {
      return absl::InvalidArgumentError(absl::StrCat("unknown flag '", flag, "' (see --help)"));
    }
    if (!value.has_value()) {
      if (i + 1 >= args.size()) return FlagError(flag, "missing value");
      value = args[++i];
    }
    if (flag == "--scene") {
      bool found = false;
      std::string known_names;
      for (const SceneInfo& info : SceneCatalog()) {
        found = found || info.name == *value;
        absl::StrAppend(&known_names, known_names.empty() ? "" : ", ", info.name);
      }
      if (!found) {
        return FlagError(flag,
                         absl::StrCat("unknown scene '", *value, "' (known: ", known_names, ")"));
      }
      o.scene = *value;
    } else if (flag == "--frames") {
      absl::StatusOr<int> frames = ParseIntFlag(flag, *value, 1, 1000000);
      if (!frames.ok()) return frames.status();
      o.frames = *frames;
    } else if (flag == "--start") {
      absl::StatusOr<int> start = ParseIntFlag(flag, *value, 0, kMaxFrameIndex - 1);
      if (!start.ok()) return start.status();
      o.start_frame = *start;
    } else if (flag == "--size") {
      const std::vector<std::string> parts = absl::StrSplit(*value, 'x');
      int w = 0;
      int h = 0;
      if (parts.size() != 2 || !absl::SimpleAtoi(parts[0], &w) || !absl::SimpleAtoi(parts[1], &h) ||
          w < 1 || h < 1 || w > 16384 || h > 16384) {
        return FlagError(flag, absl::StrCat("expected WIDTHxHEIGHT with sides in [1, 16384], got '",
                                            *value, "'"));
      }
      o.width = w;
      o.height = h;
    } else if (flag == "--seed") {
      uint64_t seed = 0;
      if (!absl::SimpleAtoi(*value, &seed)) {
        return FlagError(flag, absl::StrCat("expected a non-negative integer, got '", *value, "'"));
      }
      o.seed = seed;
    } else if (flag == "--out") {
      if (value->empty()) return FlagError(flag, "must not be empty");
      o.out_dir = *value;
      have_out = true;
    } else if (flag == "--format") {
      if (*value == "png") {
        o.format = OutputFormat::kPng;
      } else if (*value == "exr") {
        o.format = OutputFormat::kExr;
      } else if (*value == "both") {
        o.format = OutputFormat::kBoth;
      } else {
        return FlagError(flag, absl::StrCat("expected png, exr or both, got '", *value, "'"));
      }
    } else if (flag == "--threads") {
      absl::StatusOr<int> threads = ParseIntFlag(flag, *value, 1, 1024);
      if (!threads.ok()) return threads.status();
      o.threads = *threads;
    }
  }
  if (help) {
    command.action = CliCommand::Action::kHelp;
  } else if (list) {
    command.action = CliCommand::Action::kListScenes;
  } else if (!have_out) {
    return absl::InvalidArgumentError("--out: required (the output folder)");
  } else if (o.start_frame > kMaxFrameIndex - o.frames) {
    return FlagError("--start", absl::StrCat("start + frames must not exceed ", kMaxFrameIndex));
  }
  return command;
}

std::string SceneListText() {
  std::string text;
  for (const SceneInfo& info : SceneCatalog()) {
    absl::StrAppend(&text, info.name, "\t", info.description, "\n");
  }
  return text;
}

std::string UsageText() {
  return absl::StrCat(
      "Usage: framediffuser-scenegen --out DIR [--scene NAME] [--frames N] [--start K]\n"
      "                              [--size WxH] [--seed S] [--format png|exr|both]\n"
      "                              [--threads T]\n"
      "       framediffuser-scenegen --list-scenes | --help\n"
      "\n"
      "Renders a synthetic G-buffer sequence with a ray-traced ground-truth image, in the\n"
      "FrameDiffuser dataset layout. Equal arguments give byte-identical files.\n"
      "\n"
      "Flags:\n"
      "  --out DIR        output folder (created; existing files are overwritten)\n"
      "  --scene NAME     scene preset (default street; see --list-scenes)\n"
      "  --frames N       number of frames (default 24)\n"
      "  --start K        first frame index: writes frames K .. K+N-1 (default 0); frame k\n"
      "                   is the same image whatever N and K, so shards can be combined\n"
      "  --size WxH       image size in pixels (default 512x512)\n"
      "  --seed S         varies object placement, colours and sampling noise (default 0)\n"
      "  --format F       png (default), exr, or both\n"
      "  --threads T      worker threads (default: all cores); never changes the output\n"
      "  --list-scenes    print the scene presets and exit\n"
      "  --help           print this text and exit\n"
      "\n"
      "Output (frame index with 4 digits):\n"
      "  DIR/FinalImage/FinalImage_0000.png  RGB   ground truth: ACES tone map, sRGB\n"
      "  DIR/BaseColor/BaseColor_0000.png    RGB   sRGB albedo\n"
      "  DIR/Normals/Normals_0000.png        RGB   world normal (Z up) as n*0.5+0.5\n"
      "  DIR/Depth/Depth_0000.png            gray  inverse depth near/d (see below)\n"
      "  DIR/Roughness/Roughness_0000.png    gray  linear roughness\n"
      "  DIR/Metallic/Metallic_0000.png      gray  linear metallic\n"
      "  DIR/scene.json                      arguments, conventions, camera per frame\n"
      "  With --format exr|both, float .exr files sit beside the PNGs in the same folders.\n"
      "\n"
      "Depth encoding: byte = round(255 * min(1, near / d)), d = view depth in metres, near =\n"
      "the scene's near plane (in scene.json). 0 means no geometry (sky). Geometry never\n"
      "goes below 10: surfaces farther than near * 25.5 are stored as 10. Sky pixels are 0\n"
      "in every G-buffer, so the reference sky test (all BaseColor channels < 10 and\n"
      "Depth < 10) selects exactly the sky.\n"
      "\n"
      "Exit status: 0 success, 1 generation failed, 2 bad command line.\n");
}

}  // namespace fd::scenegen
