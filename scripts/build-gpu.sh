#!/usr/bin/env bash
# Builds fd::model, the model benchmark and (with gRPC) the server against a
# CUDA LibTorch -- the one inside a Python torch with CUDA -- in a separate
# build folder, then benchmarks whole SD1.5-shaped frames on the GPU.
#
# Usage: scripts/build-gpu.sh [options]
#   --torch-prefix DIR  LibTorch's CMake prefix (default: what
#                       `python3 -c 'import torch; print(torch.utils.cmake_prefix_path)'`
#                       prints; with --cpu-check: /usr, Debian's CPU LibTorch)
#   --python EXE        the Python with torch (default python3)
#   --build-dir DIR     build folder (default build/gpu; --cpu-check: build/gpu-cpu-check)
#   --model-only        no gRPC parts (FD_WITH_GRPC=OFF): fd::model + the benchmark
#   --with-grpc         with --cpu-check: build the gRPC parts and the server too
#   --with-tests        FD_BUILD_TESTS=ON, and build fd_model_test
#   --werror            FD_WERROR=ON (on by default with --cpu-check)
#   --jobs N            ninja -j N (default: ninja's own choice)
#   --cuda-arch LIST    TORCH_CUDA_ARCH_LIST for LibTorch's CMake files (default:
#                       the GPU's compute capability, e.g. 9.0; we compile no
#                       CUDA code, so CMAKE_CUDA_ARCHITECTURES is left alone)
#   --cmake-arg ARG     one more cmake argument (repeatable)
#   --bench-arg ARG     one more fd_model_bench argument (repeatable), e.g.
#                       --bench-arg=--benchmark_repetitions=3
#   --no-bench          configure and build only
#   --allow-old-abi     go on with a LibTorch built with _GLIBCXX_USE_CXX11_ABI=0
#                       (model-only; needs abseil and Google Benchmark built with
#                       the same ABI first on CMAKE_PREFIX_PATH, see below)
#   --cpu-check         no GPU needed: the same configure and build against the
#                       given (or Debian's /usr) CPU LibTorch, model-only unless
#                       --with-grpc, then a smoke run of the whole-frame
#                       benchmark on the tiny preset (64x64, 2 steps, batch 1
#                       and 2, fp32 and bf16, CPU)
#   --dry-run           print the plan (cmake / ninja / benchmark commands) only
#   -h, --help          this text
#
# The GPU benchmark: fd_model_bench BM_PresetFrame on the sd15 preset (random
# weights of SD1.5's shapes, made once into $TMPDIR: ~4.3 GB), 512x512, 10
# UniPC steps, batch 1/2/4/8, fp16 and bf16 on cuda; Google Benchmark JSON in
# <build>/bench-gpu.json (--cpu-check: <build>/bench-cpu-check.json) and a
# short table (frames/s, nominal TFLOP/s).
#
# Requirements on the GPU machine: Debian 12's build dependencies
# (scripts/setup-deps.sh), a Python torch with CUDA, and a CUDA toolkit (nvcc
# and headers, the major version of torch.version.cuda): LibTorch's CMake
# files run find_package(CUDAToolkit) and enable_language(CUDA).
#
# The C++ ABI: Debian's abseil, Google Benchmark and gRPC are built with
# _GLIBCXX_USE_CXX11_ABI=1, and fd::model itself uses abseil
# (absl::Status/StatusOr, StrCat), so our code must be compiled with the ABI of
# LibTorch AND of those libraries. A LibTorch with ABI 0 (pip wheels before
# the manylinux_2_28 switch of PyTorch 2.6/2.7) cannot be linked with them:
# this script stops and says so, unless --allow-old-abi (then gRPC is off and
# you supply ABI-0 builds of abseil and benchmark, e.g.
# --cmake-arg=-DCMAKE_PREFIX_PATH='<abseil>;<benchmark>;<torch prefix>').
set -euo pipefail

repo=$(cd "$(dirname "$0")/.." && pwd)

usage() { sed -n '2,/^set -euo/{/^set -euo/d;s/^# \{0,1\}//;p}' "$0"; }
die() {
  echo "build-gpu: $*" >&2
  exit 1
}
note() { echo "build-gpu: $*"; }

torch_prefix=""
python=python3
build_dir=""
grpc=""  # "", on, off
tests=OFF
werror=""
jobs=""
cuda_arch=""
cpu_check=0
dry_run=0
bench=1
allow_old_abi=0
cmake_extra=()
bench_extra=()

# take_value "$@": the option's value, from --name=value or the next
# argument; sets value and shift_by.
take_value() {
  if [[ $has_inline_value -eq 1 ]]; then
    shift_by=1
  else
    [[ $# -ge 2 ]] || die "$arg needs a value (see --help)"
    value=$2
    shift_by=2
  fi
}
while [[ $# -gt 0 ]]; do
  arg=$1
  value=""
  has_inline_value=0
  if [[ $arg == --*=* ]]; then
    value=${arg#*=}
    arg=${arg%%=*}
    has_inline_value=1
  fi
  shift_by=1
  case "$arg" in
    -h | --help) usage; exit 0 ;;
    --torch-prefix) take_value "$@"; torch_prefix=$value ;;
    --python) take_value "$@"; python=$value ;;
    --build-dir) take_value "$@"; build_dir=$value ;;
    --model-only) grpc=off ;;
    --with-grpc) grpc=on ;;
    --with-tests) tests=ON ;;
    --werror) werror=ON ;;
    --jobs) take_value "$@"; jobs=$value ;;
    --cuda-arch) take_value "$@"; cuda_arch=$value ;;
    --cmake-arg) take_value "$@"; cmake_extra+=("$value") ;;
    --bench-arg) take_value "$@"; bench_extra+=("$value") ;;
    --no-bench) bench=0 ;;
    --allow-old-abi) allow_old_abi=1 ;;
    --cpu-check) cpu_check=1 ;;
    --dry-run) dry_run=1 ;;
    *) die "unknown argument '$1' (see --help)" ;;
  esac
  shift "$shift_by"
done
[[ -z $jobs || $jobs =~ ^[1-9][0-9]*$ ]] || die "--jobs wants a positive integer, got '$jobs'"

if [[ $cpu_check -eq 1 ]]; then
  build_dir=${build_dir:-build/gpu-cpu-check}
  [[ -n $torch_prefix ]] || torch_prefix=/usr
  werror=${werror:-ON}
  grpc=${grpc:-off}
else
  build_dir=${build_dir:-build/gpu}
  grpc=${grpc:-on}
fi
werror=${werror:-OFF}
[[ $build_dir == /* ]] || build_dir=$repo/$build_dir

# Prints a command, shell-quoted, as the plan shows it.
show() {
  local out="  " word
  for word in "$@"; do
    if [[ $word =~ ^[][A-Za-z0-9_./=:,+@%^-]+$ ]]; then
      out+=" $word"
    else
      out+=" '${word//\'/\'\\\'\'}'"
    fi
  done
  echo "$out"
}
# Runs a command (or only shows it with --dry-run).
run() {
  show "$@"
  [[ $dry_run -eq 1 ]] || "$@"
}

# --- LibTorch: where it is, its version, CUDA and C++ ABI -------------------
torch_version="" torch_cuda="" torch_abi="" cuda_available="" gpu_name="" gpu_capability=""
if [[ -z $torch_prefix ]]; then
  # Everything in one interpreter start (importing torch takes seconds).
  if info=$("$python" - 2>/dev/null <<'EOF'
import torch
print("prefix", torch.utils.cmake_prefix_path)
print("version", torch.__version__)
print("cuda", torch.version.cuda or "")
print("abi", int(torch._C._GLIBCXX_USE_CXX11_ABI))
available = torch.cuda.is_available()
print("available", int(available))
if available:
    print("gpu", torch.cuda.get_device_name(0))
    print("capability", "%d.%d" % torch.cuda.get_device_capability(0))
EOF
  ); then
    while read -r key rest; do
      case "$key" in
        prefix) torch_prefix=$rest ;;
        version) torch_version=$rest ;;
        cuda) torch_cuda=$rest ;;
        abi) torch_abi=$rest ;;
        available) cuda_available=$rest ;;
        gpu) gpu_name=$rest ;;
        capability) gpu_capability=$rest ;;
      esac
    done <<<"$info"
  elif [[ $dry_run -eq 1 ]]; then
    note "no torch in '$python' (dry run: placeholders below)"
    torch_prefix="<torch.utils.cmake_prefix_path>"
  else
    die "'$python' cannot import torch; install a CUDA torch or pass --torch-prefix DIR"
  fi
fi

# TorchConfig.cmake below the prefix (pip: <prefix>/Torch; libtorch zip:
# share/cmake/Torch; Debian: lib/<triplet>/cmake/Torch).
torch_dir=""
for candidate in "$torch_prefix"/Torch "$torch_prefix"/share/cmake/Torch \
  "$torch_prefix"/lib/cmake/Torch "$torch_prefix"/lib/*/cmake/Torch; do
  if [[ -f $candidate/TorchConfig.cmake ]]; then
    torch_dir=$candidate
    break
  fi
done
if [[ -z $torch_dir && $torch_prefix != "<"* ]]; then
  die "no TorchConfig.cmake under $torch_prefix (tried Torch/, share/cmake/Torch/, lib/cmake/Torch/, lib/*/cmake/Torch/)"
fi
# Without Python's answers (an explicit prefix), read them from the CMake files.
if [[ -n $torch_dir && -z $torch_version ]]; then
  torch_version=$(sed -n 's/^set(PACKAGE_VERSION "\(.*\)")$/\1/p' "$torch_dir/TorchConfigVersion.cmake" 2>/dev/null || true)
  torch_abi=$(sed -n 's/.*-D_GLIBCXX_USE_CXX11_ABI=\([01]\).*/\1/p' "$torch_dir/TorchConfig.cmake" | head -n 1)
  for lib in "$torch_dir"/../../../lib/libtorch_cuda.so "$torch_dir"/../../libtorch_cuda.so; do
    [[ -e $lib ]] && torch_cuda="yes (libtorch_cuda.so)"
  done
fi

note "LibTorch: ${torch_dir:-$torch_prefix}"
note "  torch ${torch_version:-?}, CUDA ${torch_cuda:-none}, _GLIBCXX_USE_CXX11_ABI=${torch_abi:-?}"
[[ -z $gpu_name ]] || note "  GPU 0: $gpu_name (compute capability $gpu_capability)"

if [[ $torch_abi == 0 ]]; then
  if [[ $allow_old_abi -eq 0 ]]; then
    die "this LibTorch uses the old C++ ABI (_GLIBCXX_USE_CXX11_ABI=0), so our code must too;
  but fd::model links abseil (absl::Status, StatusOr, StrCat...), fd_model_bench links
  Google Benchmark and the server gRPC, and Debian builds all three with the new ABI:
  std::string in their signatures mangles differently, and the link fails (undefined
  absl::...::StrCat / Status::ToStringSlow). Turning gRPC off does not help, fd::model
  itself needs abseil. Use a LibTorch with the new ABI instead: a recent torch
  (manylinux_2_28 wheels, PyTorch 2.6/2.7 on) or the 'cxx11-abi' LibTorch zip from
  pytorch.org with --torch-prefix <libtorch>; or pass --allow-old-abi with ABI-0 builds
  of abseil and Google Benchmark first on CMAKE_PREFIX_PATH (see --help)."
  fi
  note "old C++ ABI allowed (--allow-old-abi): configuring with FD_WITH_GRPC=OFF, because"
  note "  Debian's gRPC/protobuf/abseil use the new ABI; abseil and benchmark must come from"
  note "  your own ABI-0 builds (--cmake-arg=-DCMAKE_PREFIX_PATH=...)"
  grpc=off
fi

# --- CUDA checks (GPU mode only) -------------------------------------------
nvcc=""
if [[ $cpu_check -eq 0 ]]; then
  if [[ -z $torch_cuda && $dry_run -eq 0 ]]; then
    die "this torch ($torch_version) has no CUDA (torch.version.cuda is empty); use --cpu-check on a machine without a GPU"
  fi
  # Known only from Python (an explicit --torch-prefix leaves it to the benchmark).
  if [[ $bench -eq 1 && $cuda_available == 0 && $dry_run -eq 0 ]]; then
    die "torch.cuda.is_available() is False: no usable GPU/driver here (--no-bench builds only)"
  fi
  if [[ -z $gpu_capability ]] && command -v nvidia-smi >/dev/null; then
    gpu_capability=$(nvidia-smi --query-gpu=compute_cap --format=csv,noheader 2>/dev/null | head -n 1 || true)
  fi
  # LibTorch's CMake files need the CUDA toolkit (nvcc, headers).
  candidates=("$(command -v nvcc || true)")
  [[ -z ${CUDA_HOME:-} ]] || candidates+=("$CUDA_HOME/bin/nvcc")
  [[ -z ${CUDA_PATH:-} ]] || candidates+=("$CUDA_PATH/bin/nvcc")
  candidates+=(/usr/local/cuda/bin/nvcc)
  for candidate in "${candidates[@]}"; do
    if [[ -n $candidate && -x $candidate ]]; then
      nvcc=$candidate
      break
    fi
  done
  if [[ -z $nvcc ]]; then
    [[ $dry_run -eq 1 ]] || die "no nvcc (PATH, \$CUDA_HOME/bin, /usr/local/cuda/bin): LibTorch's CMake files
  need a CUDA toolkit of torch's CUDA version ($torch_cuda), e.g. NVIDIA's cuda-toolkit-${torch_cuda%%.*}-x
  package or pip's nvidia-cuda-nvcc-cu${torch_cuda%%.*} (then CUDA_HOME=<its folder>)"
    nvcc="<nvcc>"
  else
    nvcc_version=$("$nvcc" --version | sed -n 's/.*release \([0-9.]*\).*/\1/p')
    note "  nvcc $nvcc_version: $nvcc"
    if [[ -n $torch_cuda && ${nvcc_version%%.*} != "${torch_cuda%%.*}" ]]; then
      note "  warning: nvcc $nvcc_version and torch's CUDA $torch_cuda differ in the major version"
    fi
  fi
  # Saves LibTorch's CMake files from compiling and running a GPU detection
  # program (we compile no CUDA code; the list only feeds nvcc flags).
  if [[ -z ${TORCH_CUDA_ARCH_LIST:-} ]]; then
    cuda_arch=${cuda_arch:-$gpu_capability}
  fi
fi

# --- configure ---------------------------------------------------------------
grpc_flag=$([[ $grpc == on ]] && echo ON || echo OFF)
configure=(cmake -S "$repo" -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE=Release
  "-DCMAKE_PREFIX_PATH=$torch_prefix" "-DFD_BUILD_TESTS=$tests" "-DFD_WITH_GRPC=$grpc_flag"
  "-DFD_WERROR=$werror")
# Torch_DIR too: a cached Torch_DIR from an earlier configure would win over
# CMAKE_PREFIX_PATH.
[[ -z $torch_dir ]] || configure+=("-DTorch_DIR=$torch_dir")
if command -v ccache >/dev/null; then
  configure+=(-DCMAKE_C_COMPILER_LAUNCHER=ccache -DCMAKE_CXX_COMPILER_LAUNCHER=ccache)
fi
if [[ $cpu_check -eq 0 ]]; then
  configure+=("-DCMAKE_CUDA_COMPILER=$nvcc")
  # The server measures CUDA memory (session/device_memory.cc).
  [[ $grpc == off ]] || configure+=(-DFD_WITH_CUDA=ON)
fi
configure+=("${cmake_extra[@]}")

targets=(fd_model fd_model_bench)
[[ $grpc == off ]] || targets+=(framediffuser-server)
[[ $tests == OFF ]] || targets+=(fd_model_test)
build=(ninja -C "$build_dir")
[[ -z $jobs ]] || build+=(-j "$jobs")
build+=("${targets[@]}")

# --- benchmark ---------------------------------------------------------------
bench_bin=$build_dir/bench/fd_model_bench
if [[ $cpu_check -eq 1 ]]; then
  bench_json=$build_dir/bench-cpu-check.json
  bench_cmd=("$bench_bin" '--benchmark_filter=^BM_PresetFrame/' --fd_preset=tiny --fd_device=cpu
    '--fd_dtype=fp32,bf16' --fd_size=64x64 --fd_steps=2 '--fd_batch=1,2' --fd_min_time=0.05)
else
  bench_json=$build_dir/bench-gpu.json
  threads=$(nproc 2>/dev/null || echo 2)
  ((threads <= 8)) || threads=8
  bench_cmd=("$bench_bin" '--benchmark_filter=^BM_PresetFrame/' --fd_preset=sd15 --fd_device=cuda
    '--fd_dtype=fp16,bf16' --fd_size=512x512 --fd_steps=10 '--fd_batch=1,2,4,8'
    "--fd_threads=$threads" --fd_min_time=3)
fi
bench_cmd+=("--benchmark_out=$bench_json" --benchmark_out_format=json "${bench_extra[@]}")

# A short table from the JSON (python3 is there: Debian's, or torch's).
print_table() {
  command -v python3 >/dev/null || return 0
  python3 - "$1" <<'EOF'
import json, sys
runs = [b for b in json.load(open(sys.argv[1]))["benchmarks"] if b.get("run_type") == "iteration"]
print("%-62s %10s %9s %8s" % ("benchmark", "ms/iter", "frames/s", "TFLOP/s"))
for b in runs:
    if b.get("error_occurred"):
        print("%-62s ERROR %s" % (b["name"], b.get("error_message", "")))
        continue
    ms = b["real_time"] * {"ns": 1e-6, "us": 1e-3, "ms": 1.0, "s": 1e3}[b["time_unit"]]
    tflops = "%8.1f" % b["TFLOPS"] if "TFLOPS" in b else "%8s" % "-"
    print("%-62s %10.1f %9.2f %s" % (b["name"].replace("/real_time", ""), ms,
                                      b.get("frames_per_second", 0.0), tflops))
EOF
}

echo "build-gpu: plan ($([[ $cpu_check -eq 1 ]] && echo "CPU check" || echo GPU), gRPC $grpc_flag, tests $tests)"
[[ -z $cuda_arch ]] || echo "   export TORCH_CUDA_ARCH_LIST=$cuda_arch"
[[ -z $cuda_arch ]] || export TORCH_CUDA_ARCH_LIST=$cuda_arch
run "${configure[@]}"
run "${build[@]}"
if [[ $bench -eq 1 ]]; then
  show "${bench_cmd[@]}"
  [[ $dry_run -eq 0 ]] || exit 0
  # The table also when a benchmark failed (fd_model_bench exits 1 then).
  bench_status=0
  "${bench_cmd[@]}" || bench_status=$?
  if [[ -s $bench_json ]]; then
    echo "build-gpu: results in $bench_json"
    print_table "$bench_json"
  fi
  [[ $bench_status -eq 0 ]] || die "fd_model_bench failed (exit $bench_status)"
fi
