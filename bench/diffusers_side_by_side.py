#!/usr/bin/python3
"""Times diffusers v0.31.0 (eager, Python) and fd_model_bench on the same
golden config-B weights and inputs, in interleaved rounds, and prints the
ratios (issue "CPU performance"; results in docs/BENCHMARKS.md).

Not part of CI and no diffusers code in the repository: give it a diffusers
v0.31.0 source tree (commit 89e4d621, the one the goldens come from; newer
diffusers does not import on torch 1.13) and run it with Debian's python3 and
python3-torch (apt install python3-torch python3-numpy python3-pil
python3-requests python3-filelock python3-importlib-metadata python3-regex
python3-packaging python3-tqdm):

    /usr/bin/python3 bench/diffusers_side_by_side.py --diffusers DIR \
        [--golden ../shared/golden] [--bench build/default/bench/fd_model_bench] \
        [--threads 1,2] [--rounds 3] [--json OUT.json]

What each side runs (one process per measurement, alternating Python / C++):
  * step:  ControlNet + UNet on the golden batch (2 x latent 12x16, 77 tokens,
           timestep 37): BM_UNetControlNetStep.
  * frame: batch 1 and 2 = VAE encode of the float previous frame (posterior
           sample) + 10 UniPC steps (config B's scheduler config, guidance 1,
           the golden G-buffer condition and prompt embeddings) + VAE decode
           + uint8 postprocess: BM_FullFrame/1, /2.
Equal settings on both sides: torch intra-op threads T, one OpenBLAS thread,
OMP_WAIT_POLICY=PASSIVE with GOMP_SPINCOUNT=300000 (the C++ side's own
policy), glibc malloc with the C++ side's tuning given as environment
variables (mmap threshold 32 MiB, no heap trimming), which the C++ side then
leaves as set. The C++ side merges config B's ControlLoRA into the UNet
(no cost per step); the Python side runs the UNet without it (the same
FLOPs). Medians over each side's timed iterations, then over the rounds.

huggingface_hub and safetensors are not Debian packages: their imports are
stubbed here (nothing is downloaded) and the weights are read with a small
safetensors reader, as the golden generator did. torch 1.13's baddbmm with
beta=0 reads its uninitialised output (NaN * 0); the calls are given a
zero input and beta=1 instead (the same arithmetic, as the goldens did).
"""

import argparse
import importlib.machinery
import json
import os
import re
import statistics
import subprocess
import sys
import time
import types

SPIN_COUNT = "300000"
MALLOC_ENV = {
    "MALLOC_MMAP_THRESHOLD_": str(32 * 1024 * 1024),
    "MALLOC_TRIM_THRESHOLD_": str(2**63 - 1),
}


def side_env(threads):
    env = dict(os.environ)
    env.update(MALLOC_ENV)
    env.update({
        "OMP_WAIT_POLICY": "PASSIVE",
        "GOMP_SPINCOUNT": SPIN_COUNT,
        "OPENBLAS_NUM_THREADS": "1",
        "OMP_NUM_THREADS": str(threads),
    })
    return env


# --------------------------------------------------------------------------
# The Python side (runs in its own process: --worker).


def stub_hub_modules():
    """Stand-ins for huggingface_hub and safetensors (import-time names only)."""

    class Anything(types.ModuleType):
        def __getattr__(self, name):
            if name.startswith("__"):
                raise AttributeError(name)
            if name.startswith("REGEX"):
                return re.compile(r"^[0-9a-f]{40}$")
            if name.isupper():
                return "/nonexistent-hf-home"
            if name[0].isupper():
                cls = type(name, (Exception,), {})
                setattr(self, name, cls)
                return cls

            def function(*args, **kwargs):
                return args[0] if len(args) == 1 and callable(args[0]) else None

            return function

    for name in ["huggingface_hub", "huggingface_hub.utils", "huggingface_hub.constants",
                 "huggingface_hub.file_download", "huggingface_hub._commit_api",
                 "safetensors", "safetensors.torch"]:
        module = Anything(name)
        module.__spec__ = importlib.machinery.ModuleSpec(name, None, is_package=True)
        module.__path__ = []
        module.__version__ = "0.0"
        sys.modules[name] = module
    sys.modules["huggingface_hub"].utils = sys.modules["huggingface_hub.utils"]
    sys.modules["safetensors"].torch = sys.modules["safetensors.torch"]


def read_safetensors(path):
    import numpy as np
    import torch
    dtypes = {"F32": np.float32, "F16": np.float16, "I64": np.int64, "I32": np.int32}
    with open(path, "rb") as f:
        data = f.read()
    n = int.from_bytes(data[:8], "little")
    header = json.loads(data[8:8 + n])
    out = {}
    for key, info in header.items():
        if key == "__metadata__":
            continue
        begin, end = info["data_offsets"]
        array = np.frombuffer(data[8 + n + begin:8 + n + end], dtype=dtypes[info["dtype"]])
        out[key] = torch.from_numpy(array.reshape(info["shape"]).copy())
    return out


def python_worker(args):
    import numpy as np
    import torch
    torch.set_num_threads(args.threads)
    stub_hub_modules()
    sys.path.insert(0, os.path.join(args.diffusers, "src"))
    original_baddbmm = torch.baddbmm

    def baddbmm(input, batch1, batch2, *, beta=1, alpha=1, out=None):
        if beta == 0:
            input = torch.zeros_like(input)
            beta = 1
        return original_baddbmm(input, batch1, batch2, beta=beta, alpha=alpha)

    torch.baddbmm = baddbmm
    from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
    from diffusers import UniPCMultistepScheduler

    golden = os.path.join(args.golden, "B")

    def load(cls, folder):
        with open(os.path.join(golden, folder, "config.json")) as f:
            config = json.load(f)
        model = cls.from_config(config)
        model.load_state_dict(
            read_safetensors(os.path.join(golden, folder, "diffusion_pytorch_model.safetensors")),
            strict=True)
        return model.eval()

    unet = load(UNet2DConditionModel, "unet")
    controlnet = load(ControlNetModel, "controlnet")
    vae = load(AutoencoderKL, "vae")
    with open(os.path.join(golden, "scheduler", "scheduler_config.json")) as f:
        scheduler = UniPCMultistepScheduler.from_config(json.load(f))
    inputs = read_safetensors(os.path.join(golden, "golden", "inputs.safetensors"))
    sf = vae.config.scaling_factor

    latent = inputs["noisy_latent"]
    prev = latent.flip(0)
    ehs = inputs["encoder_hidden_states"]
    cond = inputs["controlnet_cond"]
    t = inputs["timestep"]

    def step():
        down, mid = controlnet(latent, t, encoder_hidden_states=ehs, controlnet_cond=cond,
                               return_dict=False)
        return unet(torch.cat([latent, prev], 1), t, encoder_hidden_states=ehs,
                    down_block_additional_residuals=down,
                    mid_block_additional_residual=mid).sample

    def frame(batch):
        k = [i % cond.shape[0] for i in range(batch)]
        generator = torch.Generator().manual_seed(1000)
        image = inputs["prev_image"][k] * 2 - 1
        prev_latent = vae.encode(image).latent_dist.sample(generator) * sf
        x = torch.randn(prev_latent.shape, generator=generator)
        scheduler.set_timesteps(10)
        for timestep in scheduler.timesteps:
            down, mid = controlnet(x, timestep, encoder_hidden_states=ehs[k],
                                   controlnet_cond=cond[k], return_dict=False)
            eps = unet(torch.cat([x, prev_latent], 1), timestep, encoder_hidden_states=ehs[k],
                       down_block_additional_residuals=down,
                       mid_block_additional_residual=mid).sample
            x = scheduler.step(eps, timestep, x).prev_sample
        decoded = vae.decode(x / sf).sample
        pixels = (decoded / 2 + 0.5).clamp(0, 1)
        return (pixels * 255).round().to(torch.uint8).permute(0, 2, 3, 1).numpy()

    def median_ms(fn, warmup, iterations):
        for _ in range(warmup):
            fn()
        times = []
        for _ in range(iterations):
            start = time.perf_counter()
            fn()
            times.append((time.perf_counter() - start) * 1e3)
        return statistics.median(times)

    result = {}
    with torch.inference_mode():
        result["step"] = median_ms(step, 3, args.step_iterations)
        for batch in (1, 2):
            result[f"frame_b{batch}"] = median_ms(lambda: frame(batch), 1, args.frame_iterations)
    print(json.dumps(result))


# --------------------------------------------------------------------------
# The C++ side and the driver.


def cpp_side(args, threads):
    command = [args.bench, "--benchmark_filter=^BM_UNetControlNetStep|^BM_FullFrame/[12]/",
               f"--fd_threads={threads}", "--benchmark_format=json",
               f"--benchmark_repetitions={args.frame_iterations}"]
    run = subprocess.run(command, env=side_env(threads), capture_output=True, text=True,
                         check=True)
    report = json.loads(run.stdout)
    times = {}
    for b in report["benchmarks"]:
        if b.get("run_type") != "iteration":
            continue
        name = b["run_name"]
        key = ("step" if name.startswith("BM_UNetControlNetStep")
               else "frame_b" + name.split("/")[1])
        scale = {"ms": 1.0, "us": 1e-3, "ns": 1e-6, "s": 1e3}[b["time_unit"]]
        times.setdefault(key, []).append(b["real_time"] * scale)
    return {key: statistics.median(values) for key, values in times.items()}, report["context"]


def python_side(args, threads):
    command = [sys.executable, os.path.abspath(__file__), "--worker", "--threads", str(threads),
               "--diffusers", args.diffusers, "--golden", args.golden,
               "--step_iterations", str(args.step_iterations),
               "--frame_iterations", str(args.frame_iterations)]
    run = subprocess.run(command, env=side_env(threads), capture_output=True, text=True)
    if run.returncode != 0:
        sys.exit(f"the Python side failed:\n{run.stderr[-4000:]}")
    return json.loads(run.stdout.strip().splitlines()[-1])


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--diffusers", required=True, help="diffusers v0.31.0 source tree")
    parser.add_argument("--golden", default=os.path.join(here, "..", "..", "shared", "golden"))
    parser.add_argument("--bench", default=os.path.join(here, "..", "build", "default", "bench",
                                                        "fd_model_bench"))
    parser.add_argument("--threads", default="1,2")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--step_iterations", type=int, default=30)
    parser.add_argument("--frame_iterations", type=int, default=3)
    parser.add_argument("--json", help="write every measurement here")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        args.threads = int(args.threads)
        python_worker(args)
        return
    if not os.path.isdir(os.path.join(args.diffusers, "src", "diffusers")):
        sys.exit(f"--diffusers {args.diffusers}: no src/diffusers there")
    if not os.access(args.bench, os.X_OK):
        sys.exit(f"--bench {args.bench}: not an executable (build the default preset first)")
    thread_counts = [int(x) for x in args.threads.split(",")]
    rows = []
    context = None
    for r in range(args.rounds):
        for threads in thread_counts:
            py = python_side(args, threads)
            cpp, context = cpp_side(args, threads)
            rows.append({"round": r, "threads": threads, "python_ms": py, "cpp_ms": cpp})
            print(f"round {r} threads {threads}: " + ", ".join(
                f"{k} {py[k]:.1f} / {cpp[k]:.1f} ms" for k in sorted(py)), flush=True)
    print("\nmedians over the rounds (Python diffusers / C++ = speed-up)")
    print(f"{'threads':>7}  {'what':<9} {'python ms':>10} {'c++ ms':>8} {'ratio':>6}")
    summary = {}
    for threads in thread_counts:
        for key in ("step", "frame_b1", "frame_b2"):
            py = statistics.median(x["python_ms"][key] for x in rows if x["threads"] == threads)
            cpp = statistics.median(x["cpp_ms"][key] for x in rows if x["threads"] == threads)
            summary[f"{key}_t{threads}"] = {"python_ms": py, "cpp_ms": cpp, "ratio": py / cpp}
            print(f"{threads:>7}  {key:<9} {py:>10.1f} {cpp:>8.1f} {py / cpp:>5.2f}x")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"rows": rows, "summary": summary, "cpp_context": context,
                       "settings": {**MALLOC_ENV, "OMP_WAIT_POLICY": "PASSIVE",
                                    "GOMP_SPINCOUNT": SPIN_COUNT, "OPENBLAS_NUM_THREADS": "1",
                                    "OPENBLAS_CORETYPE": os.environ.get("OPENBLAS_CORETYPE", "")}},
                      f, indent=1)


if __name__ == "__main__":
    main()
