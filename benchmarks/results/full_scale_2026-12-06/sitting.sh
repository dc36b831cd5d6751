#!/usr/bin/env bash
# One sitting, the recipes stopped (not held): the Ant paper run's next iteration from its boundary checkpoint, then the floor.
set -u
OUT=/root/sitting2/out; mkdir -p $OUT
PY=/work/main/.venv/bin/python
log() { echo "$(date -u +%FT%TZ) $1 load $(cut -d' ' -f1-3 /proc/loadavg)" >> $OUT/sitting.txt; }
sleep 30; log "runs stopped"
cd /work/main && $PY -m benchmarks.full_scale /root/keep/ant --rounds 1 --out $OUT/full_scale_ant.json > $OUT/full_scale_ant.log 2>&1; log "full_scale done"
cd /work/main && $PY -m benchmarks.bounds --envs Ant-v5 --out $OUT/bounds_ant.json > $OUT/bounds_ant.log 2>&1; log "bounds done"
cd /work/main && $PY -m benchmarks.run_floor --full-scale $OUT/full_scale_ant.json --bounds $OUT/bounds_ant.json --out $OUT/run_floor_ant.json > $OUT/run_floor_ant.log 2>&1; log "run_floor done"
