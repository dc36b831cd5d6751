#!/usr/bin/env bash
# One run at the paper's budget (the schema's defaults, torchrl_esrl/run/schema.py: Section 4 and its table), run to the end across
# sessions. By default the README's main command,
#
#     python recipes/es_td3.py env=walker2d seed=0
#
# and any other with RUN (a recipe and its overrides), e.g. RUN="recipes/td3.py env=walker2d seed=0".
# Each call runs one piece: the run continues from its own checkpoints (hydra.run.dir=run_dir; a
# checkpoint every 50k TD3 frames as well as at every iteration boundary, so a killed piece loses at
# most one ES phase). While a piece runs, <run_dir>.piece<N>.alive holds its commit, start, seconds so
# far and peak resident memory (VmHWM), rewritten every 2 s, so a piece killed with its session
# still has a record. <run_dir>.pieces gets one line per piece: that record and how it ended (exit
# status, or "killed" for a piece that left only its .alive file). Once the run has written
# summary.json, its records go to $RESULTS: metrics.csv, summary.json, config.yaml, pieces.txt,
# checkpoints.txt (the size in bytes of each checkpoint kept at the end), pauses.txt (when
# scripts/pause_runs.sh held the run, if it did), arithmetic.txt (where the pieces ran on more than one
# commit: scripts/tiny_digest.sh of the recipe on each, equal digests meaning the same arithmetic); and
# the report of the one run goes to $REPORT (recipes/report.py: curves, buffer sizes, ES mean vs
# TD3 actor). A finished run is never rewritten: calling again only copies the records.
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
  record="piece $piece commit $(git rev-parse HEAD) start $(date -u +%FT%TZ)"
  t0=$(date +%s)
  # shellcheck disable=SC2086  # RUN is a recipe and its overrides, split on spaces
  "$PYTHON" $RUN hydra.run.dir="$DIR" checkpoint.every_frames=50000 "$@" \
    > "$DIR.piece$piece.log" 2>&1 &
  pid=$!
  peak=0
  while kill -0 "$pid" 2> /dev/null; do
    hwm=$(awk '/^VmHWM/ {print int($2 / 1024)}' "/proc/$pid/status" 2> /dev/null)
    if [ "${hwm:-0}" -gt "$peak" ]; then peak=$hwm; fi
    echo "$record seconds $(( $(date +%s) - t0 )) peak_rss_mib $peak" > "$DIR.piece$piece.alive"
    sleep 2
  done
  wait "$pid"
  status=$?
  echo "$record seconds $(( $(date +%s) - t0 )) peak_rss_mib $peak exit $status" >> "$DIR.pieces" && rm -f "$DIR.piece$piece.alive"
fi
[ -f "$DIR/summary.json" ] || exit 1
mkdir -p "$RESULTS" "$REPORT"
cp "$DIR/metrics.csv" "$DIR/summary.json" "$RESULTS/"
cp "$DIR/.hydra/config.yaml" "$RESULTS/config.yaml"
cp "$DIR.pieces" "$RESULTS/pieces.txt"
[ -f "$DIR.pauses" ] && cp "$DIR.pauses" "$RESULTS/pauses.txt"  # scripts/pause_runs.sh: the run held while a benchmark ran
du -sb "$DIR"/checkpoints/checkpoint-* | sed "s#$DIR/##" > "$RESULTS/checkpoints.txt"  # bytes of each checkpoint kept at the end
commits=$(awk '/^piece / && !seen[substr($4, 1, 7)]++ {printf "%s ", substr($4, 1, 7)}' "$DIR.pieces")
recipe=$(basename "${RUN%% *}")
if [ "$(echo $commits | wc -w)" -gt 1 ] && ! grep -q "^# scripts/tiny_digest.sh $recipe $commits(" "$RESULTS/arithmetic.txt" 2> /dev/null; then
  # shellcheck disable=SC2086  # one argument per commit
  digests=$(PYTHON="$PYTHON" scripts/tiny_digest.sh "$recipe" $commits) \
    && printf '# scripts/tiny_digest.sh %s %s(%s): commit, rows of the tiny preset'"'"'s metrics.csv, sha256 of the rows without wall-time columns\n%s\n' \
      "$recipe" "$commits" "$(date -u +%F)" "$digests" > "$RESULTS/arithmetic.txt"
fi
"$PYTHON" recipes/report.py "$RESULTS" --out "$REPORT" > /dev/null
