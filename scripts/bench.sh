#!/usr/bin/env bash
# The runs behind docs/results.md: HalfCheetah-v5, experiment=bench, seeds 0-2 of ES-TD3Buffers,
# TD3 and the single-buffer ES-TD3; three runs at a time by default (one torch thread each).
# Usage: scripts/bench.sh [out_dir] [parallel_jobs]
set -u
OUT=${1:-bench}
JOBS=${2:-3}
cd "$(dirname "$0")/.."
mkdir -p "$OUT"
jobs() {
  for seed in 0 1 2; do
    echo "es_td3 es_td3.py $seed"
    echo "td3 td3.py $seed"
    echo "es_td3_shared es_td3.py $seed buffer.mode=shared"
  done
}
jobs | xargs -P "$JOBS" -L 1 bash -c '
  name=$0; recipe=$1; seed=$2; shift 2
  start=$(date +%s)
  OMP_NUM_THREADS=1 python recipes/$recipe env=halfcheetah experiment=bench seed=$seed "$@" \
    hydra.run.dir='"$OUT"'/${name}_seed$seed > '"$OUT"'/log_${name}_seed$seed.txt 2>&1
  echo "$name seed $seed: exit $? after $(( $(date +%s) - start )) s" >> '"$OUT"'/timings.txt'
