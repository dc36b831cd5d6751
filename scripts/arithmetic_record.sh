#!/usr/bin/env bash
# A run's arithmetic.txt: whether the commits its attempts ran on compute the same. With two commits or
# more, scripts/tiny_digest.sh of the run's recipe on each (the tiny preset), and, where the learning
# code differs between them (git diff of torchrl_esrl, conf and recipes, the report left out), the
# same with gradient steps on the run's own task: OVERRIDES="env=<env> <the recipe's gradient steps>",
# more TD3 updates for es_td3.py and td3.py, cem.start_frames=0 for CEM-RL, whose tiny preset stops
# before its first gradient step (es.py takes none). Each block: a header line naming its command and
# date, then one line per commit (commit, rows of metrics.csv, sha256 of the rows without wall-time
# columns); equal digests: the same arithmetic bit for bit. A block already in the file is kept.
# scripts/paper_run.sh and scripts/multibuffer_experiments.sh call it as they record a run.
#
# Usage: scripts/arithmetic_record.sh <records_dir> <recipe.py> <env or -> <commit>...   PYTHON=python
#   e.g. scripts/arithmetic_record.sh docs/results/runs/paper/walker2d/td3_seed0 td3.py walker2d 5cb7dc5 d23fb75
set -u
cd "$(dirname "$0")/.."
records=$1; recipe=$2; env=$3; shift 3
commits=$(printf '%s\n' "$@" | cut -c1-7 | awk '!seen[$0]++' | tr '\n' ' ')
[ "$(echo $commits | wc -w)" -gt 1 ] || exit 0
file=$records/arithmetic.txt
learning=(torchrl_esrl conf recipes ':!torchrl_esrl/report' ':!recipes/report.py')
first=${commits%% *}
differs=
for commit in $commits; do
  git diff --quiet "$first" "$commit" -- "${learning[@]}" || differs="$first..$commit:$(git diff --shortstat "$first" "$commit" -- "${learning[@]}")"
done
case $recipe in
  cem_rl.py|cem_rl_buffers.py) steps="cem.start_frames=0" ;;
  es.py) steps= ;;
  *) steps="td3.frames_per_iteration=1000" ;;
esac

block() {  # header, then OVERRIDES for tiny_digest.sh
  header=$1; overrides=$2
  grep -qF -- "${header%%(*}(" "$file" 2> /dev/null && return 0
  # shellcheck disable=SC2086  # one argument per commit
  digests=$(OVERRIDES=$overrides scripts/tiny_digest.sh "$recipe" $commits) || return 1
  printf '%s\n%s\n' "$header" "$digests" >> "$file"
}

today=$(date -u +%F)
block "# scripts/tiny_digest.sh $recipe $commits($today): commit, rows of the tiny preset's metrics.csv, sha256 of the rows without wall-time columns" "" || exit 1
if [ -n "$differs" ] && [ -n "$steps" ]; then
  overrides=$steps
  [ "$env" = - ] || overrides="env=$env $steps"
  block "# OVERRIDES=\"$overrides\" scripts/tiny_digest.sh $recipe $commits($today): the learning code differs between these commits (git diff $differs in torchrl_esrl, conf, recipes), so with gradient steps on the run's task too: commit, rows, sha256" "$overrides" || exit 1
fi
