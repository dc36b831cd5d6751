#!/usr/bin/env bash
# One sitting, the recipes held: bounds (float32 floor, bf16), peers, and the ES evaluation with the shared-center option.
set -u
OUT=/root/sitting/out; mkdir -p $OUT
PY=/work/main/.venv/bin/python
log() { echo "$(date -u +%FT%TZ) $1 load $(cut -d' ' -f1-3 /proc/loadavg)" >> $OUT/sitting.txt; }
cd /work/main && scripts/pause_runs.sh pause >> $OUT/sitting.txt
sleep 60; log "runs held"
cd /work/main && $PY -m benchmarks.bounds --envs HalfCheetah-v5 Walker2d-v5 Ant-v5 --out $OUT/bounds.json > $OUT/bounds.log 2>&1; log "bounds done"
cd /work/main && $PY -m benchmarks.peers --out $OUT/peers.json > $OUT/peers.log 2>&1; log "peers done"
cd /work/wt/shared-center && PYTHONPATH=$PWD $PY -m benchmarks.es_population --envs Walker2d-v5 HalfCheetah-v5 Ant-v5 --repeats 3 --skip-slow --out $OUT/es_population.json > $OUT/es_population.log 2>&1; log "es_population done"
cd /work/main && scripts/pause_runs.sh resume >> $OUT/sitting.txt; log "runs resumed"
