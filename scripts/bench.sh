#!/usr/bin/env bash
# The runs behind docs/results.md: HalfCheetah-v5, experiment=bench, one torch thread per run,
# parallel_jobs runs at a time (default 2: one per core of the 2-core machine).
#   main:      seeds 0-2 of ES-TD3Buffers, TD3 and the single-buffer ES-TD3 (buffer.mode=shared)
#   baselines: seeds 0-2 of CEM-RL and OpenAI-ES, and ES-TD3Buffers seed 0 at two more ratios
#              (the ratio sweep; ratio 0.5:0.2:0.3 comes from main)
#   all:       main, then baselines
# Usage: scripts/bench.sh [out_dir] [parallel_jobs] [main|baselines|all]
set -u
OUT=${1:-bench}
JOBS=${2:-2}
SET=${3:-all}
case "$SET" in main|baselines|all) ;; *) echo "scripts/bench.sh: set must be one of main, baselines, all (got '$SET')" >&2; exit 2;; esac
cd "$(dirname "$0")/.."
mkdir -p "$OUT"
runs() {  # name recipe seed [overrides...], one run per line, in the order they start
  if [ "$SET" != baselines ]; then
    for seed in 0 1 2; do
      echo "es_td3 es_td3.py $seed"
      echo "td3 td3.py $seed"
      echo "es_td3_shared es_td3.py $seed buffer.mode=shared"
    done
  fi
  if [ "$SET" != main ]; then
    for seed in 0 1 2; do echo "cem_rl cem_rl.py $seed"; done
    echo "es_td3_ratio_0.2_0.2_0.6 es_td3.py 0 buffer.ratio=[0.2,0.2,0.6]"
    echo "es_td3_ratio_0.8_0.1_0.1 es_td3.py 0 buffer.ratio=[0.8,0.1,0.1]"
    for seed in 0 1 2; do echo "es es.py $seed"; done
  fi
}
runs | xargs -P "$JOBS" -L 1 bash -c '
  name=$0; recipe=$1; seed=$2; shift 2
  start=$(date +%s)
  OMP_NUM_THREADS=1 python recipes/$recipe env=halfcheetah experiment=bench seed=$seed "$@" \
    hydra.run.dir='"$OUT"'/${name}_seed$seed > '"$OUT"'/log_${name}_seed$seed.txt 2>&1
  echo "$name seed $seed: exit $? after $(( $(date +%s) - start )) s" >> '"$OUT"'/timings.txt'
