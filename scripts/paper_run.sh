#!/usr/bin/env bash
# One run at the paper's budget (the schema's defaults, torchrl_esrl/run/schema.py: Section 4 and its table), run to the end across
# sessions. By default the README's main command,
#
#     python recipes/es_td3.py env=walker2d seed=0
#
# and any other with RUN (a recipe and its overrides), e.g. RUN="recipes/td3.py env=walker2d seed=0".
# Each call runs one piece: the run continues from its own checkpoints (hydra.run.dir=run_dir; a
# checkpoint every 50k TD3 frames and, in ES-TD3's ES phase, every 10 generations, as well as at every
# iteration boundary, so a killed piece loses at most 50k TD3 frames or 10 generations). While a piece runs, <run_dir>.piece<N>.alive holds its commit, start, the
# processor it runs on (scripts/processor.sh: machines change between sessions), seconds so
# far, peak resident memory (VmHWM) and the machine's 1-minute load average so far (mean and largest,
# sampled every 2 s), rewritten every 2 s, so a piece killed with its session still has a record.
# <run_dir>.pieces gets one line per piece: that record and how it ended (exit status, or "killed" for a
# piece that left only its .alive file). Once the run has written summary.json, its records go to
# $RESULTS: metrics.csv, summary.json, config.yaml, pieces.txt, checkpoints.txt (the size in bytes of
# each checkpoint kept at the end), pauses.txt (when scripts/pause_runs.sh held the run, if it did; the
# report subtracts the held time: timing.md), run.log (the run's own log: each iteration's end, UTC, and
# the training clock then), arithmetic.txt (where the pieces ran on more than one commit:
# scripts/arithmetic_record.sh, equal digests meaning the same arithmetic); and the report of the one
# run goes to $REPORT (recipes/report.py: curves, buffer sizes, ES mean vs TD3 actor). A finished run
# is never rewritten: calling again only copies the records.
#
# Usage: scripts/paper_run.sh [run_dir] [extra overrides...]
#   RUN="recipes/es_td3.py env=walker2d seed=0"  RESULTS=docs/results/runs/paper/walker2d/es_td3_seed0
#   REPORT=docs/results/paper  PYTHON=python
#   e.g. nohup scripts/paper_run.sh runs_paper/walker2d/es_td3_seed0 > /dev/null 2>&1 &
#        RUN="recipes/es_td3.py env=swimmer seed=0" RESULTS=docs/results/runs/paper/swimmer/es_td3_seed0 \
#          REPORT=docs/results/paper/swimmer nohup scripts/paper_run.sh runs_paper/swimmer/es_td3_seed0 > /dev/null 2>&1 &
set -u
cd "$(dirname "$0")/.."
DIR=${1:-runs_paper/walker2d/es_td3_seed0}
shift $(( $# < 1 ? $# : 1 ))
RESULTS=${RESULTS:-docs/results/runs/paper/walker2d/es_td3_seed0}
REPORT=${REPORT:-docs/results/paper}
PYTHON=${PYTHON:-python}
RUN=${RUN:-recipes/es_td3.py env=walker2d seed=0}
mkdir -p "$(dirname "$DIR")"

for alive in "$DIR".piece*.alive; do  # pieces killed with their session: keep their last record
  [ -f "$alive" ] || continue
  echo "$(cat "$alive") killed" >> "$DIR.pieces" && rm "$alive"
done
if [ ! -f "$DIR/summary.json" ]; then
  piece=$(grep -c '^piece ' "$DIR.pieces" 2>/dev/null || true)
  piece=${piece:-0}
  cpu=$(scripts/processor.sh)
  record="piece $piece commit $(git rev-parse HEAD) start $(date -u +%FT%TZ) cpu $cpu"
  t0=$(date +%s)
  # shellcheck disable=SC2086  # RUN is a recipe and its overrides, split on spaces
  "$PYTHON" $RUN hydra.run.dir="$DIR" checkpoint.every_frames=50000 checkpoint.every_generations=10 "$@" \
    > "$DIR.piece$piece.log" 2>&1 &
  pid=$!
  peak=0 sum=0 count=0 highest=0
  load_text() { mean=$((sum / (count > 0 ? count : 1))); printf 'load_mean %d.%02d load_max %d.%02d' $((mean / 100)) $((mean % 100)) $((highest / 100)) $((highest % 100)); }
  while kill -0 "$pid" 2> /dev/null; do
    hwm=$(awk '/^VmHWM/ {print int($2 / 1024)}' "/proc/$pid/status" 2> /dev/null)
    if [ "${hwm:-0}" -gt "$peak" ]; then peak=$hwm; fi
    load=$(cut -d' ' -f1 /proc/loadavg | tr -d .) load=$((10#$load))  # hundredths
    sum=$((sum + load)) count=$((count + 1)) highest=$((load > highest ? load : highest))
    echo "$record seconds $(( $(date +%s) - t0 )) peak_rss_mib $peak $(load_text)" > "$DIR.piece$piece.alive"
    sleep 2
  done
  wait "$pid"
  status=$?
  echo "$record seconds $(( $(date +%s) - t0 )) peak_rss_mib $peak $(load_text) exit $status" >> "$DIR.pieces" && rm -f "$DIR.piece$piece.alive"
fi
[ -f "$DIR/summary.json" ] || exit 1
mkdir -p "$RESULTS" "$REPORT"
cp "$DIR/metrics.csv" "$DIR/summary.json" "$RESULTS/"
cp "$DIR/.hydra/config.yaml" "$RESULTS/config.yaml"
cp "$DIR.pieces" "$RESULTS/pieces.txt"
[ -f "$DIR.pauses" ] && cp "$DIR.pauses" "$RESULTS/pauses.txt"  # scripts/pause_runs.sh: the run held while a benchmark ran
du -sb "$DIR"/checkpoints/checkpoint-* | sed "s#$DIR/##" > "$RESULTS/checkpoints.txt"  # bytes of each checkpoint kept at the end
recipe=$(basename "${RUN%% *}")
[ -f "$DIR/${recipe%.py}.log" ] && cp "$DIR/${recipe%.py}.log" "$RESULTS/run.log"  # the run's own log: each iteration's time
# shellcheck disable=SC2086  # RUN's words
env=$(printf '%s\n' $RUN | sed -n 's/^env=//p' | tail -n 1)
# shellcheck disable=SC2046  # one argument per commit
PYTHON="$PYTHON" scripts/arithmetic_record.sh "$RESULTS" "$recipe" "${env:--}" $(awk '/^piece / {print $4}' "$DIR.pieces")
"$PYTHON" recipes/report.py "$RESULTS" --out "$REPORT" > /dev/null
