"""Whole iterations at full scale: a real run resumed from one of its checkpoints, timed per iteration,
the working tree against a past commit, alternating, in one sitting.

Small-buffer extrapolations (``benchmarks.iteration``) time a fraction of an iteration; this times
the thing itself. A copy of ``run_dir`` holding one checkpoint taken at an iteration boundary (its
buffers as the run had filled them, its episode lengths, its networks) is continued by the run's
own recipe (``recipes/<hydra.job.name>.py resume=<copy>``) until ``metrics.csv`` gains one row: the
next iteration, complete. Its time is that row's ``wall_time_s`` less the previous row's (the
training clock: start-up and checkpoint loading excluded; ``process_s`` has them included). The
recipe is then killed and the copy deleted: the run itself is only read.

With ``--base <commit>``, the same is done with that commit's recipe and package (a ``git worktree``
on the path ahead of the installed package), in the order now, base, base, now, ... so that drift of
the machine moves both. Both read the same checkpoint: the base must be able to resume it.

Usage: ``python -m benchmarks.full_scale <run_dir> [--base <commit>] [--rounds 2] [--iteration K]
[--out PATH]`` (``--iteration``: the boundary to resume from, default the newest one that leaves an
iteration to run). Hold other runs first (``scripts/pause_runs.sh pause``): the record states the
load it saw.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import save_report

ROOT = Path(__file__).resolve().parents[1]
WORK_COLUMNS = ("td3_frames", "es_frames", "td3_updates")  # what the iteration did (metrics.csv, cumulative)


def boundary_checkpoints(run_dir: Path) -> dict[int, Path]:
    """``{completed iterations: checkpoint}`` of ``run_dir``'s checkpoints taken at an iteration
    boundary (its TD3 frames are that many iterations' worth; a checkpoint taken within an
    iteration has more frames than its completed iterations account for)."""
    per_iteration = _saved_config(run_dir).get("td3", {}).get("frames_per_iteration")
    found = {}
    for manifest in sorted((run_dir / "checkpoints").glob("checkpoint-*/manifest.json")):
        metadata = json.loads(manifest.read_text())["metadata"]
        if per_iteration is None or metadata.get("td3_frames") == metadata["iteration"] * per_iteration:
            found[metadata["iteration"]] = manifest.parent
    return found


def _saved_config(run_dir: Path) -> dict:
    from omegaconf import OmegaConf

    return OmegaConf.to_container(OmegaConf.load(run_dir / ".hydra" / "config.yaml"))


def recipe_of(run_dir: Path) -> str:
    """The recipe that wrote ``run_dir`` (Hydra's job name: ``recipes/<name>.py``)."""
    from omegaconf import OmegaConf

    return f"recipes/{OmegaConf.load(run_dir / '.hydra' / 'hydra.yaml').hydra.job.name}.py"


def copy_at(run_dir: Path, checkpoint: Path, iteration: int, into: Path) -> Path:
    """A copy of ``run_dir`` that holds ``checkpoint`` (taken after ``iteration`` iterations) alone, no
    finished-run summary, and the rows of ``metrics.csv`` the checkpoint accounts for (one a
    completed iteration, byte for byte): resuming it continues the run from there."""
    copy = into / "run"
    shutil.copytree(run_dir, copy, ignore=shutil.ignore_patterns("checkpoints", "summary.json", ".lock", "*.png"))
    shutil.copytree(checkpoint, copy / "checkpoints" / checkpoint.name)
    lines = (copy / "metrics.csv").read_bytes().splitlines(keepends=True)
    (copy / "metrics.csv").write_bytes(b"".join(lines[: 1 + iteration]))
    return copy


def _rows(metrics: Path) -> list[dict]:
    if not metrics.exists():
        return []
    with metrics.open() as f:
        return [row for row in csv.DictReader(f) if row.get("wall_time_s")]


def time_iteration(tree: Path, recipe: str, run_copy: Path, rows_at_checkpoint: int, timeout_s: float) -> dict:
    """Resume ``run_copy`` with ``tree``'s recipe and package until the next iteration's row is in
    ``metrics.csv``; the row's time on the training clock and the process's seconds until then."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(tree), os.environ.get("PYTHONPATH")]))}
    start = time.perf_counter()
    log = (run_copy.parent / "recipe.log").open("w")
    process = subprocess.Popen([sys.executable, recipe, f"resume={run_copy}"], cwd=tree, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        while True:
            rows = _rows(run_copy / "metrics.csv")
            if len(rows) > rows_at_checkpoint:
                break
            if process.poll() is not None:
                raise RuntimeError(f"{recipe} in {tree} ended ({process.returncode}) before the next iteration: {(run_copy.parent / 'recipe.log').read_text()[-2000:]}")
            if time.perf_counter() - start > timeout_s:
                raise TimeoutError(f"no new iteration within {timeout_s} s")
            time.sleep(0.5)
        process_s = time.perf_counter() - start
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
        process.wait()
        log.close()
    new, previous = rows[rows_at_checkpoint], rows[rows_at_checkpoint - 1] if rows_at_checkpoint else {}

    def done(column: str, kind=float):  # the iteration's share of a cumulative column
        return kind(new[column]) - kind(previous.get(column) or 0)

    return {
        "iteration": int(new["iteration"]),
        "eval_return": float(new["eval_return"]),  # the continued run's own result (exact resume: the run's)
        "iteration_s": done("wall_time_s"),
        "work": {column: done(column, int) for column in WORK_COLUMNS if column in new},
        "process_s": process_s,
        "load_average": os.getloadavg(),
    }


def run(run_dir: Path, base: str | None = None, rounds: int = 2, iteration: int | None = None, timeout_s: float = 6 * 3600) -> dict:
    run_dir = run_dir.resolve()
    boundaries = boundary_checkpoints(run_dir)
    last = _saved_config(run_dir)["iterations"]
    usable = {k: v for k, v in boundaries.items() if k < last}
    if iteration is None and usable:
        iteration = max(usable)
    if iteration not in usable:
        raise SystemExit(f"--iteration: {iteration} has no checkpoint at its boundary in {run_dir} (allowed: {sorted(usable) or 'none'})")
    checkpoint = usable[iteration]
    recipe = recipe_of(run_dir)
    with tempfile.TemporaryDirectory() as folder:
        trees = {"now": ROOT}
        if base is not None:
            worktree = Path(folder) / "base"
            subprocess.run(["git", "worktree", "add", "--detach", str(worktree), base], cwd=ROOT, check=True, capture_output=True)
            trees["base"] = worktree
        commits = {name: subprocess.run(["git", "describe", "--always", "--dirty"], cwd=tree, capture_output=True, text=True).stdout.strip() for name, tree in trees.items()}
        times: dict[str, list[dict]] = {name: [] for name in trees}
        try:
            for index in range(rounds):
                for name in trees if index % 2 == 0 else reversed(trees):
                    scratch = Path(folder) / f"{name}_{index}"
                    scratch.mkdir()
                    copy = copy_at(run_dir, checkpoint, iteration, scratch)
                    times[name].append(time_iteration(trees[name], recipe, copy, iteration, timeout_s))
                    shutil.rmtree(scratch)
        finally:
            if base is not None:
                subprocess.run(["git", "worktree", "remove", "--force", str(trees["base"])], cwd=ROOT, capture_output=True)
    report = {
        "run_dir": str(run_dir), "recipe": recipe, "from_iteration": iteration, "checkpoint": checkpoint.name,
        "commits": commits, "rounds": rounds, "times": times,
        "iteration_s": {name: statistics.median(t["iteration_s"] for t in values) for name, values in times.items()},
    }
    if base is not None:
        ratios = [now["iteration_s"] / before["iteration_s"] for now, before in zip(times["now"], times["base"])]
        report["ratio_now_over_base"] = {"median": statistics.median(ratios), "per_round": ratios}
    return report


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path, help="a run directory with checkpoints (scripts/paper_run.sh's)")
    parser.add_argument("--base", default=None, help="a commit to time against (the code before a change)")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--iteration", type=int, default=None, help="resume from the checkpoint at this iteration boundary")
    parser.add_argument("--timeout", type=float, default=6 * 3600, help="seconds one iteration may take")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    report = save_report(run(args.run_dir, args.base, args.rounds, args.iteration, args.timeout), args.out)
    line = ", ".join(f"{name} {seconds:,.0f} s" for name, seconds in report["iteration_s"].items())
    ratio = report.get("ratio_now_over_base")
    print(f"iteration {report['from_iteration'] + 1} of {report['run_dir']}: {line}" + (f"; now/base {ratio['median']:.3f}" if ratio else ""))
    return report


if __name__ == "__main__":
    main()
