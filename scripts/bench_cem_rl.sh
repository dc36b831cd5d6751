#!/usr/bin/env bash
# CEM-RL at the bench budget (docs/results.md), seeds 0-2, started next to scripts/bench.sh at low
# priority (nice 10) so that it uses what the three main runs leave. Usage: scripts/bench_cem_rl.sh [out_dir]
set -u
OUT=${1:-bench}
cd "$(dirname "$0")/.."
mkdir -p "$OUT"
printf '%s\n' 0 1 2 | xargs -P 3 -I{} bash -c '
  start=$(date +%s)
  OMP_NUM_THREADS=1 nice -n 10 python recipes/cem_rl.py env=halfcheetah experiment=bench seed={} \
    hydra.run.dir='"$OUT"'/cem_rl_seed{} > '"$OUT"'/log_cem_rl_seed{}.txt 2>&1
  echo "cem_rl seed {}: exit $? after $(( $(date +%s) - start )) s" >> '"$OUT"'/timings.txt'
