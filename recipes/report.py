"""The report over run or multirun directories (logic in torchrl_esrl/report/).

    python recipes/report.py outputs/ multirun/2026-11-22 --out report/
    python recipes/report.py docs/results/runs/paper docs/results/runs/miniature --overview --started started.txt --out overview/

Writes results.csv/.md (Table 1: mean, std, median per env x algorithm, plus the IQM with a 95%
stratified-bootstrap CI), improvement.csv/.md (probability of improvement of ES-TD3Buffers),
pairwise.csv/.md (exact permutation test of every pair of rows, Holm-corrected per task),
aggregate.csv/.md and aggregate.png (normalised scores across 2+ tasks), runs.csv/.md (one row per
run), curves_<env>.png (against TD3 and total frames), buffers_<env>.png, es_vs_td3_<env>*.png,
ratio_sweep_<env>.png and hard_vs_soft_<env>.png; overwrites.csv/.md (per ES-TD3 row, the runs whose ES mean
was ever overwritten, and the ES mean against its own TD3 actor run by run), summary.md (per task: IQMs,
overwrites, the differences called), iterations.md (every iteration of a row's only run) and
timing.md (timing.txt, pieces.txt).

With --overview, only overview.csv/.md: the paper's Table 1 beside the runs' final returns per
experiment preset; --started names a file of runs started but not recorded ("<env id> <algorithm>
<experiment>" a line), whose cells say "running".
"""
from __future__ import annotations

import argparse
from pathlib import Path

from torchrl_esrl.report import make_overview, make_report


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs="+", help="run directories or folders holding runs (searched recursively)")
    parser.add_argument("--out", default="report", help="output folder (default: report/)")
    parser.add_argument("--overview", action="store_true", help="write only overview.md: the paper's Table 1 beside the runs")
    parser.add_argument("--started", default=None, help="with --overview: runs started and not yet recorded, one '<env id> <algorithm> <experiment>' a line")
    args = parser.parse_args(argv)
    report = make_overview(args.paths, args.out, args.started) if args.overview else make_report(args.paths, args.out)
    print(Path(report["table_md"]).read_text())
    print(f"{report['runs']} runs -> {args.out}" + (": " + ", ".join(p.name for p in report["figures"]) if report["figures"] else ""))


if __name__ == "__main__":
    main()
