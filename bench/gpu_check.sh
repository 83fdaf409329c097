#!/usr/bin/env bash
# The CUDA checks and GPU benchmarks in one bounded run, for a machine with an NVIDIA GPU, a CUDA build of torch and
# gsplat (built here on first import when it came as the JIT wheel):
#
#   bash bench/gpu_check.sh OUT_DIR [SCENE_DIR ...]
#
# Steps, each under its own time limit (seconds; a step that fails or runs out leaves its log and the rest go on):
#   env           GPU, driver, torch and nvcc versions
#   build         gsplat's CUDA extension (JIT) and, beside it, AGG's native CPU kernels
#   tests         the CUDA tests (pytest -m cuda): gsplat against the CPU kernels, densification, scenes, eval,
#                 training on CUDA and checkpoints that move between devices
#   render        bench/render.py --device cuda at 1242x375 with 1M Gaussians, SH 1 and SH 3
#   scene_NAME    bench/render_scene.py on each trained SCENE_DIR (model.pt and scene.json): serving speed on the GPU
#                 at the training resolution (and its rgb PSNR against the CPU's renders) and at 4x with all outputs
#   suite         bench/agg_suite.py synth, seed 0 at 1.0 m, AGG at the balanced preset, trained on the GPU: the
#                 record (suite_record.json) compares with the CPU record of the same case in docs/BENCHMARKS.md
#   matrix        bench/render_matrix.py --device cuda (the CPU table's matrix)
# OUT_DIR gets one log per step and steps.txt (name, exit status, seconds). Limits can be scaled with
# AGG_GPU_TIME_SCALE (e.g. 2 on a slower machine); AGG_GPU_STEPS="build tests" runs only the steps named (a scene
# step is named "scene").
set -u
OUT=${1:?usage: bash bench/gpu_check.sh OUT_DIR [SCENE_DIR ...]}
shift
mkdir -p "$OUT" && OUT=$(cd "$OUT" && pwd)
SCENES=()
for scene in "$@"; do SCENES+=("$(cd "$scene" && pwd)"); done
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
SCALE=${AGG_GPU_TIME_SCALE:-1}
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-$($PY -c \
  "import torch; print('%d.%d' % torch.cuda.get_device_capability())" 2>/dev/null)}
export MAX_JOBS=${MAX_JOBS:-$(nproc)}

step() {  # step NAME LIMIT_S COMMAND...: run COMMAND into OUT/NAME.log under a time limit
  local name=$1 limit=$(( $2 * SCALE )) t0 rc
  shift 2
  if [ -n "${AGG_GPU_STEPS:-}" ] && [[ " $AGG_GPU_STEPS " != *" ${name%%_*} "* ]]; then return 0; fi
  t0=$(date +%s)
  timeout "$limit" "$@" > "$OUT/$name.log" 2>&1
  rc=$?
  printf '%-14s rc=%-3s %4ss (limit %ss)\n' "$name" "$rc" "$(( $(date +%s) - t0 ))" "$limit" | tee -a "$OUT/steps.txt"
  return $rc
}

step env 30 bash -c "nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; nvcc --version | tail -2;
  $PY -c 'import torch, sys; print(sys.version.split()[0], torch.__version__, torch.version.cuda,
  torch.cuda.get_device_name(0))'; echo TORCH_CUDA_ARCH_LIST=\$TORCH_CUDA_ARCH_LIST MAX_JOBS=\$MAX_JOBS"

TMP=$(mktemp -d)
SUITE="bench/agg_suite.py synth --seeds 0 --noise 1.0 --variants agg --preset balanced --work $TMP/suite"
# gsplat compiles on all cores; AGG's CPU kernels (one translation unit) and the suite's bundle are made beside it.
step build 360 bash -c "$PY -c 'from agg.render import native; native.load(); print(\"native ok\")' &
  $PY -c 'import sys; sys.path.insert(0, \"bench\"); from pathlib import Path; from agg_suite import synth_bundle; print(
  synth_bundle(Path(\"$TMP/suite\"), 0, 1.0, 24, 320, 192))' &
  $PY -c 'import time; t = time.time(); from gsplat.cuda._backend import _C; print(_C and \"gsplat ok in %.0f s\"
  % (time.time() - t)); assert _C is not None'; rc=\$?; wait; exit \$rc"

step tests 180 $PY -m pytest -m cuda -q -rs -p no:cacheprovider tests/test_render_cuda.py tests/test_densify.py \
  tests/test_scene_cuda.py tests/test_train_cuda.py

step render 120 bash -c "for sh in 1 3; do
  $PY bench/render.py --generate $TMP/s1242_1m_\$sh.npz --width 1242 --height 375 --n 1000000 --sh \$sh >/dev/null &&
  $PY bench/render.py --scene $TMP/s1242_1m_\$sh.npz --device cuda --backend cuda --repeats 20 || exit 1; done"

for scene in "${SCENES[@]}"; do
  name=$(basename "$scene")
  step "scene_$name" 120 bash -c "$PY bench/render_scene.py $scene --device cuda --compare cpu --threads $(nproc) &&
    $PY bench/render_scene.py $scene --device cuda --scale 4 --outputs all"
done
step suite 300 bash -c "$PY $SUITE --device cuda && cp $TMP/suite/runs/*.json $OUT/suite_record.json"
step matrix 120 $PY bench/render_matrix.py --device cuda --backend cuda --repeats 9
rm -rf "$TMP"
