"""The report over run or multirun directories (logic in torchrl_esrl/report.py).

    python recipes/report.py outputs/ multirun/2026-11-22 --out report/

Writes results.csv/.md (Table 1: mean, std, median per env x algorithm, plus the IQM with a 95%
stratified-bootstrap CI), improvement.csv/.md (probability of improvement of ES-TD3Buffers),
pairwise.csv/.md (exact permutation test of every pair of rows, Holm-corrected per task),
aggregate.csv/.md and aggregate.png (normalised scores across 2+ tasks), runs.csv/.md (one row per
run), curves_<env>.png (against TD3 and total frames), buffers_<env>.png, es_vs_td3_<env>*.png,
ratio_sweep_<env>.png and hard_vs_soft_<env>.png.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from torchrl_esrl.report import make_report


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs="+", help="run directories or folders holding runs (searched recursively)")
    parser.add_argument("--out", default="report", help="output folder (default: report/)")
    args = parser.parse_args(argv)
    report = make_report(args.paths, args.out)
    print(Path(report["table_md"]).read_text())
    print(f"{report['runs']} runs -> {args.out}: " + ", ".join(p.name for p in report["figures"]))


if __name__ == "__main__":
    main()
