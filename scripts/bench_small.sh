#!/usr/bin/env bash
# The small-budget runs (experiment=bench_small, 8k TD3 frames): HalfCheetah-v5, seeds 0-2, one process per
# seed (one torch thread each), algorithms one after another; a smoke test of the harness, not the
# results in docs/results.md (scripts/bench.sh). Usage: scripts/bench_small.sh [out_dir]
set -u
OUT=${1:-bench_small}
cd "$(dirname "$0")/.."
run_seed() {
  seed=$1
  for recipe in "es_td3.py" "td3.py" "es_td3.py buffer.mode=shared" "cem_rl.py iterations=2 cem.population_size=4"; do
    name=$(echo "$recipe" | sed 's/\.py//; s/ buffer.mode=shared/_shared/; s/ iterations=2 cem.population_size=4//')
    OMP_NUM_THREADS=1 nice -n 5 python recipes/$recipe env=halfcheetah experiment=bench_small seed=$seed \
      logger.progress=false hydra.run.dir=$OUT/${name}_seed$seed > $OUT/log_${name}_seed$seed.txt 2>&1
  done
}
mkdir -p "$OUT"
for seed in 0 1 2; do run_seed $seed & done
wait
# OpenAI-ES alone (run after the others for docs/results.md):
#   for seed in 0 1 2; do OMP_NUM_THREADS=1 nice -n 5 python recipes/es.py env=halfcheetah experiment=bench_small seed=$seed logger.progress=false hydra.run.dir=$OUT/es_seed$seed; done
