"""The reports committed under docs/results/, each with the recipes/report.py arguments that write
it from its records, and the results page's copies of their tables.

    PYTHONPATH=. python scripts/committed_reports.py                 # every report, then the page
    PYTHONPATH=. python scripts/committed_reports.py cem_rl_buffers  # one report, then the page
    PYTHONPATH=. python scripts/committed_reports.py --list          # the commands, one a line
    PYTHONPATH=. python scripts/committed_reports.py --reading docs/results/runs/quarter/walker2d/td3_seed3
                                                   # the reports that read this record, then the page

docs/results.md copies generated tables between ``<!-- <path>.md -->`` and ``<!-- /<path>.md -->``
(paths under docs/results/); after the reports are written, each copy is replaced by its file.
tests/test_statistics.py checks that every report's tables are what these arguments write.
"""
from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results"
RESULTS_PAGE = ROOT / "docs" / "results.md"
BLOCK = re.compile(r"(<!-- ((?:\w+/)*[\w.]+\.md) -->\n)(.*?)(\n<!-- /\2 -->)", flags=re.S)


def _runs(*paths: str) -> list[str]:
    return [f"docs/results/{path}" for path in paths]


def _bench_runs() -> list[str]:
    """The `experiment=bench` set: the run folders directly under docs/results/runs/."""
    return sorted(str(path.relative_to(ROOT)) for path in (RESULTS / "runs").glob("*_seed*"))


# report folder (under docs/results/) -> recipes/report.py's arguments but --out
REPORTS = {
    "overview": [*_runs("runs/paper", "runs/miniature", "runs/quarter", "runs/cem_rl_buffers", "runs/table1"), "--overview", "--started", "docs/results/overview/started.txt"],
    "miniature": _runs("runs/miniature"),
    "quarter": _runs("runs/quarter"),
    "cem_rl_buffers": [*_runs("runs/cem_rl_buffers"), "--reference", "cem_rl_buffers", "--normalise-by", "cem_rl"],
    "table1": [*_runs("runs/table1"), "--reference", "erl_buffers", "--normalise-by", "erl"],
    "multibuffer": _runs("runs/multibuffer"),
    "paper": _runs("runs/paper/walker2d/es_td3_seed0"),
    "paper/walker2d_td3": _runs("runs/paper/walker2d/td3_seed0"),
    "paper/halfcheetah": _runs("runs/paper/halfcheetah/es_td3_seed0"),
    "paper/swimmer": _runs("runs/paper/swimmer/es_td3_seed0"),
    "paper/ant": _runs("runs/paper/ant/es_td3_seed0"),
    ".": _bench_runs(),
}


def report_arguments(folder: str, out: str | Path | None = None) -> list[str]:
    """recipes/report.py's arguments for the report in ``folder``, written to ``out`` (default: its folder)."""
    return [*REPORTS[folder], "--out", str(out if out is not None else Path("docs/results") / folder)]


def reading(path: str | Path) -> list[str]:
    """The report folders whose records include ``path`` (a run's record folder, or a folder of them)."""
    path = (ROOT / path).resolve()
    return [folder for folder, arguments in REPORTS.items()
            if any(path.is_relative_to(records) or records.is_relative_to(path)
                   for records in ((ROOT / argument).resolve() for argument in arguments if argument.startswith("docs/results/runs")))]


def sync_page(page: Path = RESULTS_PAGE, results: Path = RESULTS) -> list[str]:
    """Replace every generated table the page copies with its file; returns the paths replaced."""
    replaced = []

    def copy(match: re.Match) -> str:
        replaced.append(match.group(2))
        return match.group(1) + (results / match.group(2)).read_text().rstrip() + match.group(4)

    page.write_text(BLOCK.sub(copy, page.read_text()))
    return replaced


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="*", help=f"reports to write (default: all of {', '.join(REPORTS)})")
    parser.add_argument("--list", action="store_true", help="print each report's command and stop")
    parser.add_argument("--reading", metavar="PATH", help="write the reports whose records include PATH (instead of folders)")
    args = parser.parse_args(argv)
    if args.reading is not None:
        args.folders = reading(args.reading)
        if not args.folders:
            print(f"{args.reading}: no committed report reads it", file=sys.stderr)
            return
    unknown = [folder for folder in args.folders if folder not in REPORTS]
    if unknown:
        print(f"config error: folders: {', '.join(unknown)} (allowed: {', '.join(REPORTS)})", file=sys.stderr)
        sys.exit(2)
    if args.list:
        for folder in args.folders or REPORTS:
            print("python recipes/report.py " + " ".join(report_arguments(folder)))
        return
    from torchrl_esrl.run.algorithm_info import load_recipe

    report = load_recipe(ROOT / "recipes" / "report.py").main
    for folder in args.folders or REPORTS:
        report(report_arguments(folder))
    print(f"{RESULTS_PAGE.relative_to(ROOT)}: {len(sync_page())} generated tables copied")


if __name__ == "__main__":
    main()
