#!/usr/bin/env bash
# Boundary checkpoints after one paper iteration (buffers full) for benchmarks.full_scale: run the paper's
# config on core 0 until a checkpoint at iteration 1 (100k TD3 frames) is complete, then kill the run.
set -u
cd /work/main
for env in "$@"; do
  dir=/root/ckpt/$env
  echo "$(date -u +%FT%TZ) start $env load $(cut -d' ' -f1-3 /proc/loadavg)"
  taskset -c 0 .venv/bin/python recipes/es_td3.py env=$env seed=0 hydra.run.dir=$dir logger.progress=false > $dir.log 2>&1 &
  pid=$!
  while kill -0 $pid 2> /dev/null; do
    sleep 10
    if grep -l '"iteration": 1' $dir/checkpoints/checkpoint-*/manifest.json > /dev/null 2>&1; then
      sleep 5; kill -KILL $pid; break
    fi
  done
  wait $pid
  echo "$(date -u +%FT%TZ) done $env load $(cut -d' ' -f1-3 /proc/loadavg)"
done
