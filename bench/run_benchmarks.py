#!/usr/bin/env python3
"""The benchmark suite's single entry point: runs every layer's benchmark and
writes one JSON file with the results, the machine and the library versions.

Layers (each a binary of the build; --layers picks some):
  model     fd_model_bench (Google Benchmark): ControlNet + UNet step, VAE
            encode / decode, text encoding, whole frames (golden config B,
            `small` preset, and the tiny preset in fp32 and bf16 at batch
            1-8 through BM_PresetFrame; scripts/build-gpu.sh runs the same
            benchmark on sd15 / CUDA)
  scenegen  fd_scenegen_bench (Google Benchmark): G-buffer generation
  session   fd_session_bench: frame batcher, 1-8 sessions, both batching
            modes, peak memory and idle state per session
  session_small  the same on the `small` preset (random weights, 128x128)
  server    fd_server_bench: end-to-end gRPC loopback vs in-process
  trainer   fd_trainer_bench: optimizer steps/s of every trainer stage per
            preset, training size and intra-op threads; loader wait fraction
  lb        tests/deploy/nginx_loopback_test.py --bench: three servers behind
            nginx vs direct (needs nginx; `full` profile only)

Profiles: `smoke` (about a minute; what ctest runs to keep the suite working),
`quick` (a few minutes), `full` (what docs/BENCHMARKS.md records; tens of
minutes on 2 cores).

  python3 bench/run_benchmarks.py --build-dir build/default --profile full \\
      --out bench-results.json

The JSON: {"suite", "created", "profile", "command", "machine", "libraries",
"layers": {name: {"command", "seconds", "result"}}}; "result" is the
benchmark's own JSON (Google Benchmark's format for model and scenegen).
Exit status 1 if any layer failed or produced no result. Timings on a shared
machine vary: "machine" records the load average before and after each
layer. OPENBLAS_CORETYPE (set to Haswell in this workplace) slows OpenBLAS;
it is recorded with the machine.
"""
import argparse
import datetime
import json
import os
import platform
import shlex
import shutil
import subprocess
import sys
import tempfile
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LAYERS = ("model", "scenegen", "session", "session_small", "server", "trainer", "lb")
PACKAGES = ("libtorch-dev", "libopenblas0-pthread", "libgrpc++-dev", "libprotobuf-dev",
            "libabsl-dev", "libbenchmark-dev", "prometheus-cpp-dev", "g++", "nginx")

# Per profile: the arguments of each layer's binary ({json} = its output file).
MODEL_FILTERS = {
    "smoke": "BM_UNetControlNetStep|BM_VaeEncode|BM_VaeDecode|BM_TextEncode/golden_clip|"
             "BM_FullFrame/1/|BM_PresetFrame",
    "quick": "BM_UNetControlNetStep|BM_VaeEncode|BM_VaeDecode|BM_TextEncode|BM_FullFrame/|"
             "BM_FullFrameSmall/[12]/|BM_PresetFrame",
    "full": ".",
}
# The configurable whole-frame benchmark (BM_PresetFrame) on the tiny preset.
PRESET_FLAGS = {
    "smoke": ["--fd_preset=tiny", "--fd_dtype=fp32", "--fd_batch=1", "--fd_steps=2",
              "--fd_iterations=2"],
    "quick": ["--fd_preset=tiny", "--fd_dtype=fp32,bf16", "--fd_batch=1,2,4,8", "--fd_steps=10"],
    "full": ["--fd_preset=tiny", "--fd_dtype=fp32,bf16", "--fd_batch=1,2,4,8", "--fd_steps=10"],
}
PROFILES = {
    "smoke": {
        "model": ["--benchmark_filter=" + MODEL_FILTERS["smoke"], "--benchmark_out={json}",
                  "--benchmark_out_format=json"] + PRESET_FLAGS["smoke"],
        "scenegen": ["--benchmark_filter=128", "--benchmark_min_time=0.05",
                     "--benchmark_out={json}", "--benchmark_out_format=json"],
        "session": ["2", "2", "1", "32", "32", "--json", "{json}"],
        "session_small": ["1", "1", "1", "32", "32", "--preset", "small", "--json", "{json}"],
        "server": ["--sessions", "1,2", "--frames", "2", "--warmup", "1", "--size", "32",
                   "--steps", "2", "--threads", "1", "--in_flight", "1", "--json", "{json}"],
        "trainer": ["--presets", "tiny", "--sizes", "32", "--threads", "1", "--steps", "2",
                    "--warmup", "1", "--json", "{json}"],
    },
    "quick": {
        "model": ["--benchmark_filter=" + MODEL_FILTERS["quick"], "--benchmark_out={json}",
                  "--benchmark_out_format=json"] + PRESET_FLAGS["quick"],
        "scenegen": ["--benchmark_min_time=0.5", "--benchmark_out={json}",
                     "--benchmark_out_format=json"],
        "session": ["4", "3", "1", "80", "64", "--workers", "2", "--json", "{json}"],
        "session_small": ["2", "3", "1", "128", "128", "--workers", "2", "--preset", "small",
                          "--json", "{json}"],
        "server": ["--sessions", "1,8", "--frames", "16", "--json", "{json}"],
        "trainer": ["--presets", "tiny,small", "--sizes", "64", "--threads", "1,2", "--steps",
                    "10", "--json", "{json}"],
    },
    "full": {
        "model": ["--benchmark_repetitions=3", "--benchmark_report_aggregates_only=true",
                  "--benchmark_out={json}", "--benchmark_out_format=json"] + PRESET_FLAGS["full"],
        "scenegen": ["--benchmark_min_time=2", "--benchmark_repetitions=3",
                     "--benchmark_report_aggregates_only=true", "--benchmark_out={json}",
                     "--benchmark_out_format=json"],
        "session": ["8", "3", "1", "80", "64", "--workers", "2", "--json", "{json}"],
        "session_small": ["4", "3", "1", "128", "128", "--workers", "2", "--preset", "small",
                          "--json", "{json}"],
        "server": ["--repeats", "4", "--json", "{json}"],
        "trainer": ["--presets", "tiny,small", "--sizes", "64,128", "--threads", "1,2",
                    "--steps", "20", "--json", "{json}"],
        "lb": ["--bench", "3"],
    },
}
BINARIES = {
    "model": "bench/fd_model_bench",
    "scenegen": "tools/scenegen/fd_scenegen_bench",
    "session": "bench/fd_session_bench",
    "session_small": "bench/fd_session_bench",
    "server": "bench/fd_server_bench",
    "trainer": "bench/fd_trainer_bench",
}


def read_first(path, key, separator=":"):
    try:
        with open(path) as f:
            for line in f:
                if line.startswith(key):
                    return line.split(separator, 1)[1].strip().strip('"')
    except OSError:
        pass
    return None


def machine_info():
    load = os.getloadavg()
    return {
        "hostname": platform.node(),
        "cpu": read_first("/proc/cpuinfo", "model name"),
        "cpus": os.cpu_count(),
        "memory": read_first("/proc/meminfo", "MemTotal"),
        "kernel": platform.release(),
        "os": read_first("/etc/os-release", "PRETTY_NAME=", "=") or platform.platform(),
        "load_average_at_start": list(load),
        "openblas_coretype": os.environ.get("OPENBLAS_CORETYPE", ""),
        "openblas_note": ("OPENBLAS_CORETYPE=Haswell (this workplace's setting) slows OpenBLAS"
                          if os.environ.get("OPENBLAS_CORETYPE") == "Haswell" else ""),
        "omp_wait_policy": bench_environment()["OMP_WAIT_POLICY"],
    }


def library_versions():
    versions = {}
    if shutil.which("dpkg-query"):
        for package in PACKAGES:
            result = subprocess.run(["dpkg-query", "-W", "-f", "${Version}", package],
                                    capture_output=True, text=True)
            versions[package] = result.stdout.strip() if result.returncode == 0 else None
    return versions


def git_commit():
    try:
        result = subprocess.run(["git", "-C", REPO, "rev-parse", "HEAD"], capture_output=True,
                                text=True, timeout=10)
        dirty = subprocess.run(["git", "-C", REPO, "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10)
        if result.returncode == 0:
            return result.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        pass
    return None


def bench_environment():
    """The benchmarks' environment: OpenMP threads sleep when idle (PASSIVE;
    the binaries would re-execute themselves with it anyway, as
    framediffuser-server does). On 2 cores the default (ACTIVE) spinning made
    the config-B step 1.5x slower (docs/BENCHMARKS.md). An explicit
    OMP_WAIT_POLICY is kept and recorded."""
    env = dict(os.environ)
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    return env


def layer_command(layer, args, json_path):
    profile = PROFILES[args.profile]
    if layer == "lb":
        build = args.build_dir
        return [sys.executable, os.path.join(REPO, "tests/deploy/nginx_loopback_test.py"),
                "--server", os.path.join(build, "server/framediffuser-server"),
                "--client", os.path.join(build, "client_sdk/framediffuser-client"),
                "--scenegen", os.path.join(build, "tools/scenegen/framediffuser-scenegen"),
                "--template", os.path.join(REPO, "deploy/nginx/framediffuser-grpc.conf.template")
                ] + profile["lb"]
    binary = os.path.join(args.build_dir, BINARIES[layer])
    return [binary] + [a.replace("{json}", json_path) for a in profile[layer]]


def run_layer(layer, args, tmp):
    json_path = os.path.join(tmp, layer + ".json")
    command = layer_command(layer, args, json_path)
    if not os.access(command[0], os.X_OK):
        return {"command": command, "error": "%s is not built (cmake --build %s)" %
                (command[0], args.build_dir)}
    print("== %s: %s" % (layer, " ".join(shlex.quote(c) for c in command)), flush=True)
    start = time.monotonic()
    load_before = os.getloadavg()[0]
    result = subprocess.run(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            errors="replace", cwd=REPO, env=bench_environment())
    seconds = time.monotonic() - start
    sys.stdout.write(result.stdout)
    entry = {"command": command, "seconds": round(seconds, 3), "exit_code": result.returncode,
             "load_average_before": load_before, "load_average_after": os.getloadavg()[0]}
    if result.returncode != 0:
        entry["error"] = "exit code %d" % result.returncode
        entry["output_tail"] = result.stdout[-4000:]
        return entry
    if layer == "lb":
        # The load-balancer benchmark prints its medians; keep its lines.
        entry["result"] = {"lines": [line for line in result.stdout.splitlines()
                                     if "median" in line or line.startswith("round ")]}
        if not entry["result"]["lines"]:
            entry["error"] = "no result lines"
        return entry
    try:
        with open(json_path) as f:
            entry["result"] = json.load(f)
    except (OSError, ValueError) as e:
        entry["error"] = "no JSON result: %s" % e
    return entry


def check_result(layer, entry):
    """What a layer's result must contain; returns an error or None."""
    if "error" in entry:
        return entry["error"]
    result = entry["result"]
    if layer in ("model", "scenegen"):
        names = [b.get("name", "") for b in result.get("benchmarks", [])]
        if not names:
            return "no benchmarks ran"
        if any(b.get("error_occurred") for b in result["benchmarks"]):
            return "a benchmark reported an error"
        if layer == "model":
            for wanted in ("BM_UNetControlNetStep", "BM_VaeEncode", "BM_VaeDecode",
                           "BM_TextEncode", "BM_FullFrame", "BM_PresetFrame"):
                if not any(n.startswith(wanted) for n in names):
                    return "missing %s" % wanted
    elif layer in ("session", "session_small"):
        modes = {(r["mode"], r["sessions"]) for r in result.get("rows", [])}
        want = {(m, s) for m in ("whole-frame", "step-level") for s in (1, 2, 4, 8)}
        if modes != want:
            return "rows %s, want both modes x 1/2/4/8 sessions" % sorted(modes)
    elif layer == "server":
        modes = {r["mode"] for r in result.get("rows", [])}
        if not {"grpc", "in-process"} <= modes:
            return "rows for %s, want grpc and in-process" % sorted(modes)
    elif layer == "trainer":
        stages = {r["stage"] for r in result.get("rows", [])}
        want = {"stage0-vae", "stage0-decoder", "stage0-base", "stage1", "stage2", "stage3"}
        if stages != want:
            return "rows for stages %s, want %s" % (sorted(stages), sorted(want))
    return None


def summary(layers):
    lines = []
    for layer, entry in layers.items():
        if "result" not in entry:
            lines.append("%-8s FAILED: %s" % (layer, entry.get("error")))
            continue
        result = entry["result"]
        if layer in ("model", "scenegen"):
            for b in result.get("benchmarks", []):
                if b.get("run_type") == "aggregate" and b.get("aggregate_name") != "median":
                    continue
                extra = ""
                if "items_per_second" in b:
                    extra = "  %.3f frames/s" % b["items_per_second"]
                lines.append("%-8s %-40s %10.2f %s%s" % (layer, b["name"], b["real_time"],
                                                         b.get("time_unit", ""), extra))
        elif layer in ("session", "session_small"):
            for r in result["rows"]:
                lines.append("%-8s %-11s %d sessions %8.2f frames/s  peak RSS %.0f MB" %
                             (layer, r["mode"], r["sessions"], r["frames_per_second"],
                              r["peak_rss_bytes"] / 1048576.0))
        elif layer == "server":
            for r in result["rows"]:
                vs = r.get("vs_inprocess")
                lines.append("%-8s %-10s %d sessions in_flight %d %8.2f frames/s%s" %
                             (layer, r["mode"], r["sessions"], r["in_flight"],
                              r["frames_per_second"], "  x%.3f" % vs if vs else ""))
        elif layer == "trainer":
            for r in result["rows"]:
                lines.append("%-8s %-5s %3dx%-3d %d thread(s) %-11s %8.2f steps/s  wait %.1f%%" %
                             (layer, r["preset"], r["size"], r["size"], r["threads"], r["stage"],
                              r["steps_per_s"], 100 * r["loader_wait_fraction"]))
        else:
            lines.extend("%-8s %s" % (layer, line) for line in result["lines"])
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--build-dir", default=os.path.join(REPO, "build/default"))
    parser.add_argument("--profile", choices=sorted(PROFILES), default="quick")
    parser.add_argument("--layers", default=None,
                        help="comma-separated subset of %s (default: the profile's)" %
                        ",".join(LAYERS))
    parser.add_argument("--out", default=None,
                        help="result file (default: <build-dir>/bench-results-<profile>.json)")
    args = parser.parse_args()
    args.build_dir = os.path.abspath(args.build_dir)
    layers = [l for l in LAYERS if l in PROFILES[args.profile]]
    if args.layers:
        wanted = args.layers.split(",")
        unknown = [l for l in wanted if l not in LAYERS]
        if unknown:
            parser.error("--layers: unknown %s (known: %s)" % (unknown, ",".join(LAYERS)))
        missing = [l for l in wanted if l not in PROFILES[args.profile]]
        if missing:
            parser.error("--layers: %s not in profile %s" % (missing, args.profile))
        layers = wanted
    out = args.out or os.path.join(args.build_dir, "bench-results-%s.json" % args.profile)

    report = {
        "suite": "framediffuser-server benchmarks",
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "profile": args.profile,
        "command": [sys.executable] + sys.argv,
        "git_commit": git_commit(),
        "machine": machine_info(),
        "libraries": library_versions(),
        "layers": {},
    }
    failures = []
    with tempfile.TemporaryDirectory(prefix="fd_bench_") as tmp:
        for layer in layers:
            entry = run_layer(layer, args, tmp)
            error = check_result(layer, entry)
            if error:
                entry["error"] = error
                failures.append("%s: %s" % (layer, error))
            report["layers"][layer] = entry
    report["machine"]["load_average_at_end"] = list(os.getloadavg())
    with open(out, "w") as f:
        json.dump(report, f, indent=2)
        f.write("\n")
    print("\n== summary (%s profile; %s)" % (args.profile, out))
    print(summary(report["layers"]))
    if failures:
        print("FAILED: " + "; ".join(failures), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
