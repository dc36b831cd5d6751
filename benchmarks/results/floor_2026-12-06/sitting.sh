#!/usr/bin/env bash
# One sitting, the recipes held: bounds (float32 floor, bf16), peers, and the ES evaluation against raw physics.
set -u
OUT=${OUT:-benchmarks/results/floor_2026-12-06}; mkdir -p $OUT
PY=${PY:-python}
log() { echo "$(date -u +%FT%TZ) $1 load $(cut -d' ' -f1-3 /proc/loadavg)" >> $OUT/sitting.txt; }
scripts/pause_runs.sh pause >> $OUT/sitting.txt
sleep 60; log "runs held"
$PY -m benchmarks.bounds --envs HalfCheetah-v5 Walker2d-v5 Ant-v5 --out $OUT/bounds.json > $OUT/bounds.log 2>&1; log "bounds done"
$PY -m benchmarks.peers --out $OUT/peers.json > $OUT/peers.log 2>&1; log "peers done"
$PY -m benchmarks.es_population --envs Walker2d-v5 HalfCheetah-v5 Ant-v5 --repeats 3 --skip-slow --out $OUT/es_population.json > $OUT/es_population.log 2>&1; log "es_population done"
scripts/pause_runs.sh resume >> $OUT/sitting.txt; log "runs resumed"
