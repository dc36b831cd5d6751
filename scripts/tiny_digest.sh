#!/usr/bin/env bash
# Whether commits compute the same: runs a recipe's tiny preset (python recipes/<recipe> experiment=tiny)
# on each commit, in a worktree of its own, and prints one line per commit: the commit, the rows of its
# metrics.csv and the sha256 of those rows without their wall-time columns (wall_time_s and every
# column ending in _s), which are the only ones that may differ between two runs of the same code.
# Equal digests: the commits compute the same metrics.csv bit for bit. A run at the paper's budget
# that spans commits (scripts/paper_run.sh) records this as its arithmetic.txt.
#
# Usage: scripts/tiny_digest.sh <recipe.py> <commit>...      e.g. scripts/tiny_digest.sh es_td3.py c08b91b fd992fb
#   OVERRIDES="<hydra overrides>" are added to each run, e.g. OVERRIDES=cem.start_frames=0 for CEM-RL,
#   whose tiny preset stops before its first gradient step;
#   WORK=<dir> keeps the worktrees and runs there (default: a temporary directory, removed with its
#   worktrees at the end); PYTHON=python
set -u
recipe=$1; shift
repo=$(cd "$(dirname "$0")/.." && pwd)
PYTHON=${PYTHON:-python}
if [ -z "${WORK:-}" ]; then
  WORK=$(mktemp -d)
  trap 'for tree in "$WORK"/tree-*; do [ -d "$tree" ] && git -C "$repo" worktree remove --force "$tree"; done; rm -rf "$WORK"' EXIT
fi
for commit in "$@"; do
  tree=$WORK/tree-$commit
  [ -d "$tree" ] || git -C "$repo" worktree add -f --detach "$tree" "$commit" > /dev/null 2>&1 || { echo "$commit: no such commit" >&2; exit 2; }
  # shellcheck disable=SC2086  # OVERRIDES: several, split on purpose
  (cd "$tree" && PYTHONPATH=$tree "$PYTHON" "recipes/$recipe" experiment=tiny ${OVERRIDES:-} hydra.run.dir="$WORK/run-$commit" > "$WORK/run-$commit.log" 2>&1) \
    || { echo "$commit: the run failed, see $WORK/run-$commit.log" >&2; exit 1; }
  "$PYTHON" - "$commit" "$WORK/run-$commit/metrics.csv" <<'PY'
import csv, hashlib, sys

commit, path = sys.argv[1], sys.argv[2]
with open(path) as f:
    rows = [[value for key, value in row.items() if not key.endswith("_s")] for row in csv.DictReader(f)]
print(commit, len(rows), "rows", hashlib.sha256(repr(rows).encode()).hexdigest())
PY
done
