#!/usr/bin/env bash
# benchmarks.peers with each method in a process of its own, default settings, the recipes held.
set -u
OUT=${OUT:-benchmarks/results/floor_2026-12-06}; PY=${PY:-python}
log() { echo "$(date -u +%FT%TZ) $1 load $(cut -d' ' -f1-3 /proc/loadavg)" >> $OUT/peers_processes.txt; }
scripts/pause_runs.sh pause >> $OUT/peers_processes.txt
sleep 30; log "runs held"
$PY -m benchmarks.peers --out $OUT/peers_processes.json > /tmp/peers_processes.log 2>&1; log "peers done"
scripts/pause_runs.sh resume >> $OUT/peers_processes.txt; log "runs resumed"
