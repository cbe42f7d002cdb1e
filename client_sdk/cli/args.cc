#include "client_sdk/cli/args.h"

#include <map>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"

namespace fd::client::cli {
namespace {

absl::Status FlagError(const std::string& flag, const std::string& message) {
  return absl::InvalidArgumentError(absl::StrCat(flag, ": ", message));
}

template <typename T>
absl::StatusOr<T> ParseNumber(const std::string& flag, const std::string& value, T lo, T hi) {
  T parsed{};
  if (!absl::SimpleAtoi(value, &parsed) || parsed < lo || parsed > hi) {
    return FlagError(
        flag, absl::StrCat("expected an integer in [", lo, ", ", hi, "], got '", value, "'"));
  }
  return parsed;
}

template <typename E>
absl::StatusOr<E> ParseChoice(const std::string& flag, const std::string& value,
                              const std::map<std::string, E>& choices) {
  auto it = choices.find(value);
  if (it != choices.end()) return it->second;
  std::string known;
  for (const auto& [name, unused] : choices)
    absl::StrAppend(&known, known.empty() ? "" : ", ", name);
  return FlagError(flag, absl::StrCat("unknown value '", value, "' (one of: ", known, ")"));
}

// Flags that take a value, per command ("" = global).
const std::map<std::string, std::vector<std::string>>& ValueFlags() {
  static const auto* flags = new std::map<std::string, std::vector<std::string>>{
      {"", {"--server", "--tls-ca", "--token"}},
      {"health", {"--service"}},
      {"render",
       {"--env", "--input", "--output", "--sequence", "--keyframe", "--frames", "--steps", "--seed",
        "--scheduler", "--sky-mode", "--format", "--exr-values", "--video", "--fps",
        "--max-in-flight"}},
      {"eval", {"--pred", "--gt", "--csv", "--plot", "--frames"}},
  };
  return *flags;
}

const std::map<std::string, std::vector<std::string>>& BoolFlags() {
  static const auto* flags = new std::map<std::string, std::vector<std::string>>{
      {"", {"--tls", "--no-failover", "--help"}},
      {"render", {"--keyframe-from-input", "--side-by-side"}},
  };
  return *flags;
}

bool Listed(const std::map<std::string, std::vector<std::string>>& table,
            const std::string& command, const std::string& flag) {
  for (const std::string& scope : {std::string(), command}) {
    auto it = table.find(scope);
    if (it == table.end()) continue;
    for (const std::string& f : it->second) {
      if (f == flag) return true;
    }
  }
  return false;
}

absl::Status Apply(Command& command, const std::string& name, const std::string& flag,
                   const std::string& value) {
  ConnectionArgs& c = command.connection;
  RenderArgs& r = command.render;
  EvalArgs& e = command.eval;
  if (flag == "--server") {
    if (value.empty()) return FlagError(flag, "empty address");
    c.server = value;
  } else if (flag == "--tls-ca") {
    c.tls_ca_file = value;
    c.tls = true;
  } else if (flag == "--token") {
    c.token = value;
  } else if (flag == "--service") {
    command.health.service = value;
  } else if (flag == "--env") {
    r.environment = value;
  } else if (flag == "--input") {
    r.input = value;
  } else if (flag == "--output") {
    r.output = value;
  } else if (flag == "--sequence") {
    r.sequence = value;
  } else if (flag == "--keyframe") {
    r.keyframe_file = value;
  } else if (flag == "--frames") {
    absl::StatusOr<FrameRange> range = ParseFrameRange(value);
    if (!range.ok()) return FlagError(flag, std::string(range.status().message()));
    (name == "eval" ? e.frames : r.frames) = *range;
  } else if (flag == "--steps") {
    absl::StatusOr<uint32_t> steps = ParseNumber<uint32_t>(flag, value, 1, 1000);
    if (!steps.ok()) return steps.status();
    r.steps = *steps;
  } else if (flag == "--seed") {
    absl::StatusOr<uint64_t> seed = ParseNumber<uint64_t>(flag, value, 0, UINT64_MAX);
    if (!seed.ok()) return seed.status();
    r.seed = *seed;
  } else if (flag == "--scheduler") {
    absl::StatusOr<Scheduler> s = ParseChoice<Scheduler>(flag, value,
                                                         {{"unipc", Scheduler::kUniPC},
                                                          {"dpmpp_2m", Scheduler::kDpmSolverPP2M},
                                                          {"ddim", Scheduler::kDdim},
                                                          {"euler", Scheduler::kEuler}});
    if (!s.ok()) return s.status();
    r.scheduler = *s;
  } else if (flag == "--sky-mode") {
    absl::StatusOr<SkyMode> s = ParseChoice<SkyMode>(flag, value,
                                                     {{"client_image", SkyMode::kClientImage},
                                                      {"previous_output", SkyMode::kPreviousOutput},
                                                      {"off", SkyMode::kOff}});
    if (!s.ok()) return s.status();
    r.sky_mode = *s;
  } else if (flag == "--format") {
    absl::StatusOr<std::string> f =
        ParseChoice<std::string>(flag, value, {{"png", "png"}, {"exr", "exr"}});
    if (!f.ok()) return f.status();
    r.format = *f;
  } else if (flag == "--exr-values") {
    absl::StatusOr<ExrValues> v = ParseChoice<ExrValues>(
        flag, value, {{"wire", ExrValues::kWire}, {"linear", ExrValues::kLinear}});
    if (!v.ok()) return v.status();
    r.exr_values = *v;
  } else if (flag == "--video") {
    r.video = value;
  } else if (flag == "--fps") {
    absl::StatusOr<int> fps = ParseNumber<int>(flag, value, 1, 240);
    if (!fps.ok()) return fps.status();
    r.fps = *fps;
  } else if (flag == "--max-in-flight") {
    absl::StatusOr<uint32_t> n = ParseNumber<uint32_t>(flag, value, 1, 64);
    if (!n.ok()) return n.status();
    r.max_in_flight = *n;
  } else if (flag == "--pred") {
    e.pred = value;
  } else if (flag == "--gt") {
    e.gt = value;
  } else if (flag == "--csv") {
    e.csv = value;
  } else if (flag == "--plot") {
    e.plot = value;
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<FrameRange> ParseFrameRange(const std::string& text) {
  FrameRange range;
  const size_t colon = text.find(':');
  auto parse = [&](const std::string& part, std::optional<int64_t>* out) -> absl::Status {
    if (part.empty()) return absl::OkStatus();
    int64_t value = 0;
    if (!absl::SimpleAtoi(part, &value) || value < 0) {
      return absl::InvalidArgumentError(
          absl::StrCat("expected A:B with frame numbers >= 0, got '", text, "'"));
    }
    *out = value;
    return absl::OkStatus();
  };
  if (colon == std::string::npos) {
    if (absl::Status s = parse(text, &range.first); !s.ok()) return s;
    if (!range.first) return absl::InvalidArgumentError("expected A:B, got ''");
    range.end = *range.first + 1;
    return range;
  }
  if (absl::Status s = parse(text.substr(0, colon), &range.first); !s.ok()) return s;
  if (absl::Status s = parse(text.substr(colon + 1), &range.end); !s.ok()) return s;
  if (range.first && range.end && *range.end <= *range.first) {
    return absl::InvalidArgumentError(
        absl::StrCat("empty range '", text, "' (A:B is A inclusive to B exclusive)"));
  }
  return range;
}

absl::StatusOr<Command> ParseCommandLine(const std::vector<std::string>& args,
                                         const std::string& token_from_env) {
  Command command;
  command.connection.token = token_from_env;
  std::string name;
  bool help = false;
  // The command is the first argument that is neither a flag nor a flag's
  // value; global value flags before it take their value along.
  std::vector<std::pair<std::string, std::string>> flags;  // flag, value ("" for bools)
  std::vector<std::string> bools;
  for (size_t i = 0; i < args.size(); ++i) {
    const std::string& arg = args[i];
    if (arg == "-h") {
      help = true;
      continue;
    }
    if (!absl::StartsWith(arg, "--")) {
      if (name.empty()) {
        name = arg;
        continue;
      }
      return absl::InvalidArgumentError(
          absl::StrCat("unexpected argument '", arg, "' (flags start with --)"));
    }
    std::string flag = arg;
    std::optional<std::string> value;
    if (const size_t eq = arg.find('='); eq != std::string::npos) {
      flag = arg.substr(0, eq);
      value = arg.substr(eq + 1);
    }
    auto anywhere = [&](const std::map<std::string, std::vector<std::string>>& table) {
      for (const auto& [scope, list] : table) {
        for (const std::string& f : list) {
          if (f == flag) return true;
        }
      }
      return false;
    };
    if (!name.empty() && !Listed(ValueFlags(), name, flag) && !Listed(BoolFlags(), name, flag) &&
        (anywhere(ValueFlags()) || anywhere(BoolFlags()))) {
      return absl::InvalidArgumentError(
          absl::StrCat(flag, ": not a flag of '", name, "' (see --help)"));
    }
    const bool takes_value =
        Listed(ValueFlags(), name, flag) || (name.empty() && anywhere(ValueFlags()));
    if (takes_value) {
      if (!value.has_value()) {
        if (i + 1 >= args.size()) return FlagError(flag, "missing value");
        value = args[++i];
      }
      flags.emplace_back(flag, *value);
      continue;
    }
    if (anywhere(BoolFlags())) {
      if (value.has_value()) return FlagError(flag, "takes no value");
      bools.push_back(flag);
      continue;
    }
    return absl::InvalidArgumentError(absl::StrCat("unknown flag '", flag, "' (see --help)"));
  }
  for (const std::string& flag : bools) {
    if (flag == "--help") help = true;
  }
  if (help || name.empty() || name == "help") {
    command.kind = Command::Kind::kHelp;
    return command;
  }
  static const std::map<std::string, Command::Kind> kCommands = {{"envs", Command::Kind::kEnvs},
                                                                 {"health", Command::Kind::kHealth},
                                                                 {"render", Command::Kind::kRender},
                                                                 {"eval", Command::Kind::kEval}};
  auto it = kCommands.find(name);
  if (it == kCommands.end()) {
    return absl::InvalidArgumentError(
        absl::StrCat("unknown command '", name, "' (envs, health, render, eval; see --help)"));
  }
  command.kind = it->second;
  for (const auto& [flag, value] : flags) {
    if (!Listed(ValueFlags(), name, flag)) {
      return absl::InvalidArgumentError(
          absl::StrCat(flag, ": not a flag of '", name, "' (see --help)"));
    }
    if (absl::Status s = Apply(command, name, flag, value); !s.ok()) return s;
  }
  for (const std::string& flag : bools) {
    if (!Listed(BoolFlags(), name, flag)) {
      return absl::InvalidArgumentError(
          absl::StrCat(flag, ": not a flag of '", name, "' (see --help)"));
    }
    if (flag == "--tls") command.connection.tls = true;
    if (flag == "--no-failover") command.connection.failover = false;
    if (flag == "--keyframe-from-input") command.render.keyframe_from_input = true;
    if (flag == "--side-by-side") command.render.side_by_side = true;
  }
  if (command.kind == Command::Kind::kRender) {
    const RenderArgs& r = command.render;
    for (const auto& [flag, value] :
         {std::pair{"--env", &r.environment}, std::pair{"--input", &r.input},
          std::pair{"--output", &r.output}}) {
      if (value->empty()) return FlagError(flag, "required for render");
    }
    if (!r.keyframe_file.empty() && r.keyframe_from_input) {
      return absl::InvalidArgumentError(
          "--keyframe and --keyframe-from-input: choose one keyframe source");
    }
    if (r.side_by_side && r.video.empty()) {
      return absl::InvalidArgumentError("--side-by-side: needs --video FILE");
    }
  }
  if (command.kind == Command::Kind::kEval) {
    if (command.eval.pred.empty()) return FlagError("--pred", "required for eval");
    if (command.eval.gt.empty()) return FlagError("--gt", "required for eval");
  }
  return command;
}

std::string UsageText() {
  return R"(framediffuser-client: talk to a FrameDiffuser server, render sequences, evaluate them.

Usage: framediffuser-client [GLOBAL FLAGS] COMMAND [FLAGS]

Commands:
  envs      List the server's environments and their readiness.
  health    grpc.health.v1 status of the server (or --service NAME).
  render    Render a G-buffer sequence from a dataset folder.
  eval      PSNR and SSIM of rendered frames against ground truth.

Global flags:
  --server ADDR        server address (default localhost:50051)
  --tls                use TLS with the system root certificates
  --tls-ca FILE        use TLS and trust the PEM roots in FILE
  --token TOKEN        bearer token (default: $FRAMEDIFFUSER_TOKEN)
  --no-failover        fail instead of re-opening the session when the stream breaks
  --help, -h           this text

render flags:
  --env NAME           environment (required; see `envs`)
  --input DIR          sequence in the authors' layout (required): DIR/BaseColor/BaseColor_0000.png,
                       Normals/, Depth/, Roughness/, optional Metallic/ and FinalImage/
                       ([<Seq>_]<Buffer>_<digits>.png|jpg|jpeg|exr), or multi-layer EXR frames
  --output DIR         where frames go: DIR/FinalImage/FinalImage_<frame>.png|exr (required)
  --sequence NAME      which <Seq> prefix to read when DIR holds several
  --keyframe FILE      RGB image used as the frame before the first one
  --keyframe-from-input
                       use the input's FinalImage of the frame before the first (or of the
                       first frame itself, as the authors do) as the keyframe
  --frames A:B         frame numbers A (inclusive) to B (exclusive); "A:", ":B", "A" also work
  --steps N            denoising steps per frame (default: the environment's)
  --seed S             session seed (default: the server picks)
  --scheduler NAME     unipc | dpmpp_2m | ddim | euler (default: the environment's)
  --sky-mode NAME      client_image | previous_output | off (default: the environment's);
                       client_image sends the input's FinalImage as the sky
  --format png|exr     output files (default png; exr writes float16 frames)
  --exr-values wire|linear
                       how EXR inputs are encoded (default wire: as sent; linear: scene-linear
                       basecolor, normals in [-1, 1], like framediffuser-scenegen's EXRs)
  --video FILE.mp4     also encode the output as a video (needs ffmpeg)
  --side-by-side       video panels: ground truth | ours | basecolor | irradiance
  --fps N              video frame rate (default 30)
  --max-in-flight N    frames uploaded ahead (default 2)

eval flags:
  --pred DIR           rendered frames (a render --output folder, or any folder of
                       <name>_<digits>.png|jpg|exr files)
  --gt DIR             ground truth (a dataset folder with FinalImage/, or such a folder)
  --csv FILE           per-frame metrics as CSV (frame,psnr_db,ssim) plus a mean row
  --plot FILE.png      PSNR and SSIM over frames as an image
  --frames A:B         restrict to these frame numbers

Metrics: PSNR over all RGB values in [0, 1] (+inf for identical frames; the mean skips them);
SSIM with an 11x11 Gaussian window (sigma 1.5), K1 0.01, K2 0.03, per RGB channel, averaged.

Exit status: 0 success, 1 failure (unreachable server, bad input, failed frames), 2 bad usage.
)";
}

}  // namespace fd::client::cli
