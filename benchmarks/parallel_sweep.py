"""A Hydra joblib sweep of two jobs on one machine against the same two jobs run one after the other.

    python -m benchmarks.parallel_sweep --rounds 2 --out benchmarks/results/parallel_sweep.json

Each round times, in turn, (a) ``seed=0`` then ``seed=1`` as two single runs and (b) the sweep
``-m hydra/launcher=joblib hydra.launcher.n_jobs=2 seed=0,1``: the recipe's whole command each time
(start-up, training, final evaluation). The ratio sweep / sequential below 1 means the sweep uses the
machine; above 1, its jobs fight over the cores (each job's threads: ``torchrl_esrl/threads.py``).
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import save_report

ROOT = Path(__file__).resolve().parents[1]


def timed(command: list[str]) -> float:
    start = time.perf_counter()
    result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{result.stderr[-2000:]}")
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--overrides", nargs="*", default=["experiment=quick", "env=halfcheetah", "iterations=2"], help="the jobs' budget")
    parser.add_argument("--out", default="benchmarks/results/parallel_sweep.json")
    args = parser.parse_args(argv)
    recipe = [sys.executable, str(ROOT / "recipes" / "es_td3.py")]
    rounds: dict[str, list[float]] = {"sequential": [], "joblib_sweep": []}
    with tempfile.TemporaryDirectory() as work:
        for r in range(args.rounds):
            runs = [recipe + [*args.overrides, f"seed={seed}", "logger.progress=false", f"hydra.run.dir={work}/seq{r}_{seed}"] for seed in (0, 1)]
            rounds["sequential"].append(sum(timed(command) for command in runs))
            sweep = recipe + ["-m", *args.overrides, "seed=0,1", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "logger.progress=false", f"hydra.sweep.dir={work}/sweep{r}"]
            rounds["joblib_sweep"].append(timed(sweep))
            threads = [json.loads(p.read_text())["threads"] for p in sorted(Path(work, f"sweep{r}").glob("*/summary.json"))]
            print(f"round {r + 1}: sequential {rounds['sequential'][-1]:.1f} s, joblib sweep {rounds['joblib_sweep'][-1]:.1f} s, the sweep's threads {threads}", flush=True)
    median = {name: statistics.median(values) for name, values in rounds.items()}
    report = {
        "command": "python -m benchmarks.parallel_sweep " + " ".join(argv or sys.argv[1:]),
        "overrides": args.overrides,
        "rounds_s": rounds,
        "median_s": median,
        "sweep_over_sequential": median["joblib_sweep"] / median["sequential"],
        "sweep_threads": threads,
    }
    save_report(report, args.out)
    print(json.dumps({k: report[k] for k in ("median_s", "sweep_over_sequential")}, indent=2))
    return report


if __name__ == "__main__":
    main()
