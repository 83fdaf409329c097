#!/usr/bin/env bash
# Synthetic-suite runs side by side on one GPU, each under a time limit, their records and logs packed in one file:
#
#   bash bench/gpu_seeds.sh OUT_DIR SEEDS VARIANTS [LIMIT_S [AGG_SUITE_ARGS ...]]
#   e.g. bash bench/gpu_seeds.sh /tmp/out 0,1,2,3,4,5,6,7,8 agg 420
#
# One process per (seed, variant), one torch thread each, all at once (a run at 320x192 keeps the GPU busy a small
# part of its time; on an H200 one balanced run took 201 s alone). The bundles are made first, one process per
# seed. Each run prints a line per topology evolution to its log, so a run stopped at LIMIT_S still says what
# evolution did. OUT_DIR gets seeds.tgz (runs/*.json: the records bench/agg_suite.py writes; log_sSEED_VARIANT.txt)
# and seeds.txt (one line per run: exit status and seconds). NOISE (default 1.0), PRESET (default balanced) and
# DEVICE (default cuda) set the case; with cuda, gsplat must be built already (bench/gpu_check.sh's build step).
set -u
OUT=${1:?usage: bash bench/gpu_seeds.sh OUT_DIR SEEDS VARIANTS [LIMIT_S [AGG_SUITE_ARGS ...]]}
SEEDS=${2:?seeds, e.g. 0,1,2}
VARIANTS=${3:?variants, e.g. agg,baseline}
LIMIT=${4:-420}
shift $(( $# < 4 ? $# : 4 ))
mkdir -p "$OUT" && OUT=$(cd "$OUT" && pwd)
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
NOISE=${NOISE:-1.0}
PRESET=${PRESET:-balanced}
DEVICE=${DEVICE:-cuda}
WORK=$(mktemp -d)
for s in ${SEEDS//,/ }; do
  $PY -c "import sys; sys.path.insert(0, 'bench'); from pathlib import Path; from agg_suite import synth_bundle
synth_bundle(Path('$WORK'), $s, $NOISE, 24, 320, 192)" &
done
wait
for s in ${SEEDS//,/ }; do
  for v in ${VARIANTS//,/ }; do
    ( t0=$(date +%s)
      timeout "$LIMIT" $PY bench/agg_suite.py synth --seeds "$s" --noise "$NOISE" --variants "$v" --preset "$PRESET" \
        --device "$DEVICE" --work "$WORK" "$@" > "$WORK/log_s${s}_$v.txt" 2>&1
      echo "s$s $v rc=$? $(( $(date +%s) - t0 ))s" >> "$OUT/seeds.txt" ) &
  done
done
wait
(cd "$WORK" && tar czf "$OUT/seeds.tgz" runs log_*.txt 2>/dev/null || tar czf "$OUT/seeds.tgz" log_*.txt)
rm -rf "$WORK"
