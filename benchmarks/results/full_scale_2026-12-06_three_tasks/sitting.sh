#!/usr/bin/env bash
# One sitting, the recipe runs held (scripts/pause_runs.sh): each paper run's second iteration from its boundary
# checkpoint after one iteration (buffers full), then the floor's parts (bounds, es_population), then run_floor.
set -u
OUT=/root/sitting3/out  # copied here; mkdir -p $OUT
PY=/work/main/.venv/bin/python
log() { echo "$(date -u +%FT%TZ) $1 load $(cut -d' ' -f1-3 /proc/loadavg)" >> $OUT/sitting.txt; }
cd /work/main
scripts/pause_runs.sh pause /root/runs/paper/ant/es_td3_seed0 >> $OUT/holds.txt  # the quarter run is held since the checkpoints were made
sleep 30; log "runs held"
for env in halfcheetah walker2d swimmer; do
  $PY -m benchmarks.full_scale /root/ckpt/$env --rounds 1 --iteration 1 --out $OUT/full_scale_$env.json > $OUT/full_scale_$env.log 2>&1; log "full_scale $env done"
done
$PY -m benchmarks.bounds --envs HalfCheetah-v5 Walker2d-v5 Swimmer-v5 --out $OUT/bounds.json > $OUT/bounds.log 2>&1; log "bounds done"
$PY -m benchmarks.es_population --envs HalfCheetah-v5 Walker2d-v5 Swimmer-v5 --repeats 2 --skip-slow --out $OUT/es_population.json > $OUT/es_population.log 2>&1; log "es_population done"
scripts/pause_runs.sh resume >> $OUT/holds.txt; log "runs resumed"
for env in halfcheetah walker2d swimmer; do
  $PY -m benchmarks.run_floor --full-scale $OUT/full_scale_$env.json --bounds $OUT/bounds.json --es-population $OUT/es_population.json --out $OUT/run_floor_$env.json > $OUT/run_floor_$env.log 2>&1
done
log "run_floor done"
