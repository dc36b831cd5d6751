#!/usr/bin/env bash
# The experiment sets behind docs/results.md, "Does the multi-buffer help?". SET picks the set and its
# preset (experiment=$SET); parallel_jobs runs at a time (default 2: one per core of a 2-core machine),
# each on its share of the cores (TORCHRL_ESRL_JOBS=parallel_jobs: TD3 and ES threads, torchrl_esrl/threads.py),
# so two runs never oversubscribe the two cores. Runs start seed by seed, so a partial set is balanced.
#
# SET=miniature (conf/experiment/miniature.yaml: the paper's schedule at 4%, K = M/4), 80 runs:
#   HalfCheetah-v5, Walker2d-v5, Swimmer-v5 and Ant-v5, seeds 0-4 of: ES-TD3Buffers 0.5:0.2:0.3; one
#   shared buffer (buffer.mode=shared); TD3 (Fujimoto's uniform warm-up, K = 1,000 frames: conf/td3.yaml);
#   OpenAI-ES.
# SET=quarter (conf/experiment/quarter.yaml: the paper's schedule at 25%, K = M/4), 30 runs: Walker2d-v5
#   first, then HalfCheetah-v5, seeds 0-4 of: ES-TD3Buffers 0.5:0.2:0.3; one shared buffer
#   (buffer.mode=shared); TD3 (Fujimoto's uniform warm-up, K = 6,250 frames).
# SET=table1 (the miniature's preset and scaling), 30 runs: HalfCheetah-v5 and Walker2d-v5, seeds 0-4 of the
#   rows of the paper's Table 1 that have no other set: CEM (recipes/cem.py), ERL (recipes/erl.py) and ERL with
#   the return-routed MultiBuffer (recipes/erl_buffers.py), each counting every env frame toward the TD3 rows'
#   (i + 1) x M frames at iteration i, ERL's learner copied into the population every generation (erl.sync_period=1:
#   the authors' 10 generations at 4%, rounded up; docs/deviations.md).
# SET=cem_rl_buffers (the miniature's preset and scaling), 20 runs: HalfCheetah-v5 and Walker2d-v5, seeds
#   0-4 of CEM-RL and of CEM-RL with the return-routed MultiBuffer (recipes/cem_rl_buffers.py): 80k frames
#   each, 8 iterations of one 10-member generation (td3.frames_per_iteration=10000), K = 1,000, the
#   reference's cem.start_frames (10,000: learning from the second generation on).
# SET=multibuffer (conf/experiment/multibuffer.yaml, the earlier 2% set), 66 runs:
#   HalfCheetah-v5 and Walker2d-v5, seeds 0-4 of: ES-TD3Buffers 0.5:0.2:0.3; one shared buffer; soft
#   overwrite (overwrite.mode=soft, mix 0.5); TD3 (warm-up K = 5,000 frames); CEM-RL (one 10-member
#   generation per iteration, 4 x 10,000 frames, start_frames scaled to 5,000); OpenAI-ES.  Ratio sweep
#   on HalfCheetah: 0.2:0.2:0.6 and 0.8:0.1:0.1, seeds 0-2 (0.5:0.2:0.3 comes from the main rows).
#
# Resumes from what exists: a run whose record is already in $RESULTS is skipped; one that finished in
# work_dir is recorded; one killed after a checkpoint continues from it (same hydra.run.dir); one killed
# before any checkpoint was complete starts over. Every finished run's metrics.csv, summary.json and
# config.yaml are copied to $RESULTS/<env>/<row>_seed<k>/ (commit each with the reports that read it,
# written by scripts/committed_reports.py --reading <record>; COMMIT=1 does both as each one lands),
# with timing.txt: one line per attempt (exit status, seconds of the command, the commit it ran on,
# its start (UTC), the mean and largest 1-minute load average over it, sampled every 2 s, the processor
# it ran on (scripts/processor.sh: machines change between sessions); a started-over
# run's earlier attempts first, marked "(started over)"), so a resumed run's wall-clock is the sum of its
# lines; an attempt killed with its script or session has its line too, marked "exit killed",
# from <run_dir>.alive, which holds the running attempt's line, rewritten every 2 s, and which the next attempt
# folds into timing.txt; pauses.txt where scripts/pause_runs.sh held the run (its seconds include the held
# time, which recipes/report.py subtracts: timing.md); run.log, the run's own log (each iteration's end,
# UTC, and the training clock then, which places the holds); and arithmetic.txt where its kept attempts
# ran on more than one commit (scripts/arithmetic_record.sh). A recorded run's checkpoints are then deleted
# (KEEP_CHECKPOINTS=1 keeps them): a finished run is never continued, and at SET=miniature the 80
# runs' checkpoints would need about 60 GB (an ES-TD3Buffers run on Ant keeps two of 2.7 GB).
#
# Usage: scripts/multibuffer_experiments.sh [work_dir] [parallel_jobs] [extra hydra overrides...]
#   SET=multibuffer  RESULTS=docs/results/runs/$SET  PYTHON=python  COMMIT=0  KEEP_CHECKPOINTS=0   (environment, defaults shown)
#   ONLY=<regex> runs only the lines 'env row recipe seed ...' it matches, e.g. ONLY='^walker2d td3 '
#   Report: python recipes/report.py docs/results/runs/$SET --out docs/results/$SET
#   e.g. SET=miniature COMMIT=1 scripts/multibuffer_experiments.sh runs_miniature 2
set -u
SET=${SET:-multibuffer}
WORK=${1:-runs_$SET}
JOBS=${2:-2}
shift $(( $# < 2 ? $# : 2 ))
cd "$(dirname "$0")/.."
case $SET in cem_rl_buffers|table1) PRESET=${PRESET:-miniature} ;; *) PRESET=${PRESET:-$SET} ;; esac
export SET PRESET WORK JOBS EXTRA="$*" RESULTS=${RESULTS:-docs/results/runs/$SET} PYTHON=${PYTHON:-python} COMMIT=${COMMIT:-0} KEEP_CHECKPOINTS=${KEEP_CHECKPOINTS:-0}
ONLY=${ONLY:-.}
mkdir -p "$WORK" "$RESULTS"

runs() {  # env row recipe seed [overrides...], one run per line, in the order they start
  case $SET in
    miniature)
      for seed in 0 1 2 3 4; do
        for env in halfcheetah walker2d swimmer ant; do
          echo "$env es_td3 es_td3.py $seed"
          echo "$env es_td3_shared es_td3.py $seed buffer.mode=shared"
          echo "$env td3 td3.py $seed"
          echo "$env es es.py $seed"
        done
      done ;;
    multibuffer)
      for seed in 0 1 2 3 4; do
        for env in halfcheetah walker2d; do
          echo "$env es_td3 es_td3.py $seed"
          echo "$env es_td3_shared es_td3.py $seed buffer.mode=shared"
          echo "$env es_td3_soft es_td3.py $seed overwrite.mode=soft overwrite.mix=0.5"
          echo "$env td3 td3.py $seed"
          echo "$env cem_rl cem_rl.py $seed iterations=4 td3.frames_per_iteration=10000 cem.start_frames=5000"
          echo "$env es es.py $seed"
        done
        if [ "$seed" -le 2 ]; then
          echo "halfcheetah es_td3_ratio_0.2_0.2_0.6 es_td3.py $seed buffer.ratio=[0.2,0.2,0.6]"
          echo "halfcheetah es_td3_ratio_0.8_0.1_0.1 es_td3.py $seed buffer.ratio=[0.8,0.1,0.1]"
        fi
      done ;;
    quarter)
      for env in walker2d halfcheetah; do
        for seed in 0 1 2 3 4; do
          echo "$env es_td3 es_td3.py $seed"
          echo "$env es_td3_shared es_td3.py $seed buffer.mode=shared"
          echo "$env td3 td3.py $seed"
        done
      done ;;
    table1)
      for seed in 0 1 2 3 4; do
        for env in halfcheetah walker2d; do
          echo "$env cem cem.py $seed"
          echo "$env erl erl.py $seed erl.sync_period=1"
          echo "$env erl_buffers erl_buffers.py $seed erl.sync_period=1"
        done
      done ;;
    cem_rl_buffers)
      for seed in 0 1 2 3 4; do
        for env in halfcheetah walker2d; do
          echo "$env cem_rl cem_rl.py $seed iterations=8 td3.frames_per_iteration=10000"
          echo "$env cem_rl_buffers cem_rl_buffers.py $seed iterations=8 td3.frames_per_iteration=10000"
        done
      done ;;
    *) echo "unknown SET=$SET (miniature | quarter | table1 | multibuffer | cem_rl_buffers)" >&2; return 1 ;;
  esac
}

run_one() {
  env=$1; row=$2; recipe=$3; seed=$4; shift 4
  name=${row}_seed$seed
  dest=$RESULTS/$env/$name
  dir=$WORK/$env/$name
  if [ -f "$dest/summary.json" ]; then echo "$env $name: recorded, skipped"; return 0; fi
  if [ -f "$dir.alive" ]; then  # an attempt killed with its script or session: its line as it last stood
    mkdir -p "$dir" && cat "$dir.alive" >> "$dir/timing.txt" && rm -f "$dir.alive"
  fi
  if [ ! -f "$dir/summary.json" ]; then
    earlier=
    if [ -d "$dir" ] && ! compgen -G "$dir/checkpoints/checkpoint-*" > /dev/null; then  # killed before any checkpoint: start over
      earlier=$(cat "$dir/timing.txt" 2> /dev/null)  # (its first iteration's row may be in metrics.csv: the recipe refuses to continue that)
      rm -rf "$dir"
    fi
    mkdir -p "$(dirname "$dir")"
    start=$(date +%s) started=$(date -u +%FT%TZ) commit=$(git rev-parse HEAD)
    cpu=$(scripts/processor.sh)
    # shellcheck disable=SC2086  # EXTRA: several overrides, split on purpose
    # TORCHRL_ESRL_JOBS: JOBS runs share the machine, each takes its share of the cores (torchrl_esrl/threads.py)
    TORCHRL_ESRL_JOBS=$JOBS "$PYTHON" "recipes/$recipe" env="$env" experiment="$PRESET" seed="$seed" "$@" $EXTRA \
      logger.progress=false hydra.run.dir="$dir" > "$dir.log" 2>&1 &
    pid=$! sum=0 count=0 peak=0
    line() {  # this attempt's timing line: exit status $1
      local mean=$((sum / (count > 0 ? count : 1)))
      printf '%s: exit %s after %s s on commit %s started %s load_mean %d.%02d load_max %d.%02d cpu %s\n' "$env $name" "$1" "$(( $(date +%s) - start ))" \
        "$commit" "$started" $((mean / 100)) $((mean % 100)) $((peak / 100)) $((peak % 100)) "$cpu"
    }
    while kill -0 "$pid" 2> /dev/null; do  # the machine's 1-minute load average, in hundredths, every 2 s
      load=$(cut -d' ' -f1 /proc/loadavg | tr -d .) load=$((10#$load))
      sum=$((sum + load)) count=$((count + 1)) peak=$((load > peak ? load : peak))
      line killed > "$dir.alive.tmp" && mv "$dir.alive.tmp" "$dir.alive"
      sleep 2
    done
    wait "$pid"
    status=$?
    mkdir -p "$dir"
    if [ -n "$earlier" ]; then printf '%s\n' "$earlier" | sed '/(started over)$/!s/$/ (started over)/' >> "$dir/timing.txt"; fi
    line "$status" | tee -a "$WORK/timings.txt" >> "$dir/timing.txt"
    rm -f "$dir.alive"
  fi
  [ -f "$dir/summary.json" ] || return 1
  mkdir -p "$dest"
  cp "$dir/metrics.csv" "$dir/summary.json" "$dest/"
  cp "$dir/.hydra/config.yaml" "$dest/config.yaml"
  if [ -f "$dir/timing.txt" ]; then cp "$dir/timing.txt" "$dest/"; fi
  if [ -f "$dir.pauses" ]; then cp "$dir.pauses" "$dest/pauses.txt"; fi  # scripts/pause_runs.sh: held while a benchmark ran
  if [ -f "$dir/${recipe%.py}.log" ]; then cp "$dir/${recipe%.py}.log" "$dest/run.log"; fi  # the run's own log: each iteration's time
  # shellcheck disable=SC2046  # one argument per commit the run's kept attempts ran on
  # env -u WORK: tiny_digest.sh reads WORK as the folder to keep its runs in; the set's WORK holds its runs
  env -u WORK scripts/arithmetic_record.sh "$dest" "$recipe" "$env" $(grep -v '(started over)$' "$dest/timing.txt" 2> /dev/null | sed -n 's/.* on commit \([0-9a-f]*\).*/\1/p') \
    || echo "$env $name: arithmetic.txt not written (scripts/arithmetic_record.sh failed)" >&2
  if [ "$KEEP_CHECKPOINTS" != 1 ]; then rm -rf "$dir/checkpoints"; fi
  # COMMIT=1: the record with the committed reports that read it (tests/test_statistics.py holds them equal)
  if [ "$COMMIT" = 1 ]; then flock "$WORK/.git.lock" sh -c '"$4" scripts/committed_reports.py --reading "$1" > /dev/null && git add "$1" docs/results docs/results.md \
    && git commit -q -m "results: $2 (experiment=$3)" -- "$1" docs/results docs/results.md' _ "$dest" "$env $name" "$PRESET" "$PYTHON"; fi
}
export -f run_one

runs | grep -E -- "$ONLY" | xargs -r -P "$JOBS" -L 1 bash -c 'run_one "$@"' _
