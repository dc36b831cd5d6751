"""The report over run or multirun directories (logic in torchrl_esrl/report/).

    python recipes/report.py outputs/ multirun/2026-11-22 --out report/
    python recipes/report.py docs/results/runs/paper docs/results/runs/miniature --overview \
        --started started.txt --out overview/

Writes results.csv/.md (Table 1: mean, std, median per env x algorithm, plus the IQM with a 95%
stratified-bootstrap CI), improvement.csv/.md (probability of improvement of --reference),
pairwise.csv/.md (exact permutation test of every pair of rows, Holm-corrected per task, and the
smallest shift of a row that test would call), aggregate.csv/.md and aggregate.png (scores normalised
by --normalise-by across 2+ tasks), runs.csv/.md (one row per run: its overwrites, its training clock
net of holds with the held time beside), curves_<env>.png (against TD3 and total frames),
buffers_<env>.png, es_vs_td3_<env>*.png, ratio_sweep_<env>.png and hard_vs_soft_<env>.png;
overwrites.csv/.md (per ES-TD3 row, the overwrites of each run, the runs whose ES mean was ever
overwritten, and the ES mean against its own TD3 actor run by run), summary.md (per task: IQMs,
overwrites, the differences called), iterations.md (every iteration of a row's only run) and
timing.md (timing.txt, pieces.txt: each run's seconds net of its holds, pauses.txt; an attempt
missing from the record).

With --overview, only overview.csv/.md: the paper's Table 1 (--paper-table, a CSV) beside the
runs' final returns per experiment preset; --started names a file of runs started but not recorded
("<env id> <algorithm> <experiment>" a line), whose cells say "running".

Labels and row order: every recipe's ALGORITHMS in this folder (torchrl_esrl/run/algorithm_info.py);
an algorithm no recipe declares is shown by its name.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from torchrl_esrl.report import Algorithms, make_overview, make_report
from torchrl_esrl.run.algorithm_info import discover

PAPER_TABLE = Path(__file__).resolve().parents[1] / "docs" / "results" / "paper_table1.csv"  # Table 1 as printed


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs="+", help="run directories or folders holding runs (searched recursively)")
    parser.add_argument("--out", default="report", help="output folder (default: report/)")
    option = parser.add_argument
    option("--overview", action="store_true", help="write only overview.md: the paper's Table 1 beside the runs")
    option("--paper-table", default=str(PAPER_TABLE), help=(
        "with --overview: the paper's table, one 'env,task,algorithm,label,mean,std,median' row per entry "
        "(default: %(default)s)"))
    option("--started", default=None, help=(
        "with --overview: runs started and not yet recorded, one '<env id> <algorithm> <experiment>' a line"))
    option("--reference", default="es_td3_buffers", help=(
        "the row every other is compared to, at the paper's ratio (default: %(default)s)"))
    option("--normalise-by", default="td3", help=(
        "the row whose mean final return is 1 on the aggregate's scale (default: %(default)s)"))
    option("--es-alone", default="es", help=(
        "the row a never-overwritten ES mean is checked against, seed by seed (default: %(default)s)"))
    option("--overview-order", default="es_td3_buffers,es_td3_shared,td3,es,cem_rl", help=(
        "with --overview: the algorithms of its first rows, comma-separated; the others follow in row order "
        "(default: %(default)s)"))
    args = parser.parse_args(argv)
    # Built here, not at import: discover() imports every recipe of this folder, this one too.
    infos = discover(Path(__file__).parent)
    rows = {"--reference": args.reference, "--normalise-by": args.normalise_by, "--es-alone": args.es_alone}
    for flag, name in rows.items():
        if name not in infos:
            allowed = ", ".join(sorted(infos))
            print(f"config error: {flag}: {name!r} is no recipe's algorithm (allowed: {allowed})", file=sys.stderr)
            sys.exit(2)
    if args.overview and not Path(args.paper_table).is_file():
        allowed = f"a CSV of the paper's table, as {PAPER_TABLE.name}"
        print(f"config error: --paper-table: {args.paper_table} is not a file (allowed: {allowed})", file=sys.stderr)
        sys.exit(2)
    algorithms = Algorithms(infos, reference=args.reference, normalise_by=args.normalise_by, es_alone=args.es_alone)
    if args.overview:
        first_rows = tuple(filter(None, args.overview_order.split(",")))
        report = make_overview(args.paths, args.out, algorithms, args.paper_table, args.started, first_rows)
    else:
        report = make_report(args.paths, args.out, algorithms)
    print(Path(report["table_md"]).read_text())
    figures = ", ".join(p.name for p in report["figures"])
    print(f"{report['runs']} runs -> {args.out}" + (f": {figures}" if figures else ""))


if __name__ == "__main__":
    main()
