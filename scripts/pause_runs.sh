#!/usr/bin/env bash
# Pause or resume recipe runs started with hydra.run.dir= (as scripts/paper_run.sh starts them), so that a
# benchmark gets the machine alone without the runs losing work: SIGSTOP holds each run (and its
# workers) where it is, in memory; SIGCONT lets it go on. Each run directory gets one line per call
# in <run_dir>.pauses ("pause <UTC time>" / "resume <UTC time>"), which paper_run.sh copies into the
# run's records as pauses.txt: the run's wall clock (metrics.csv's wall_time_s, pieces.txt's seconds)
# includes the paused time.
#
# Usage: scripts/pause_runs.sh pause|resume [run_dir ...]   (the named runs only; default: every run)
set -u
case "${1:-}" in
  pause) signal=STOP ;;
  resume) signal=CONT ;;
  *) echo "usage: scripts/pause_runs.sh pause|resume [run_dir ...]" >&2; exit 2 ;;
esac
action=$1
shift
only=("$@")
now=$(date -u +%FT%TZ)
for pid in $(pgrep -f "recipes/.*\.py .*hydra\.run\.dir="); do
  dir=$(tr '\0' '\n' < "/proc/$pid/cmdline" 2> /dev/null | sed -n 's/^hydra\.run\.dir=//p')
  [ -n "$dir" ] || continue
  if [ ${#only[@]} -gt 0 ]; then
    match=0
    for wanted in "${only[@]}"; do [ "$(realpath -m "$wanted")" = "$(realpath -m "$dir")" ] && match=1; done
    [ $match = 1 ] || continue
  fi
  pkill "-$signal" -P "$pid" 2> /dev/null  # its workers (ES chunks, the resource tracker)
  kill "-$signal" "$pid" && echo "$action $now" >> "$dir.pauses" && echo "$action $pid $dir"
done
