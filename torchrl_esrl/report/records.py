"""The runs a report reads and how it groups them.

A *run* is a directory holding ``summary.json`` and ``metrics.csv`` as written by
:class:`torchrl_esrl.run.harness.RunHarness`; any directory above runs (a Hydra multirun, a folder
of runs) is searched recursively. A row of a table is an (env, algorithm, ratio): runs at different
good:bad:noisy ratios are different configurations and never pooled.
"""
from __future__ import annotations

import csv
import json
import math
from collections import defaultdict
from pathlib import Path

from torchrl_esrl.run.metrics import read_metrics
from torchrl_esrl.run.plot import ES_TD3_BUFFERS, TD3_ACTOR_SUFFIX, label, ratio_text  # noqa: F401  (the report's names)

PAPER_RATIO = "0.5:0.2:0.3"  # the curves show ES-TD3Buffers at this ratio when runs tie
ROW_ORDER = ("es_td3_buffers", "es_td3_buffers_soft", "es_td3_shared", "es_td3_shared_soft", "td3", "cem_rl", "es")


def seeds_text(count: int) -> str:
    return f"{count} seed" + ("s" if count != 1 else "")


def find_runs(paths) -> list[dict]:
    """Every run under ``paths``: its summary, its metrics rows and its directory. A run reached
    twice (overlapping paths, a symlink) counts once."""
    runs, seen = [], set()
    for root in map(Path, paths):
        for summary_path in sorted(root.rglob("summary.json")):
            metrics_path, resolved = summary_path.with_name("metrics.csv"), summary_path.resolve()
            if not metrics_path.exists() or resolved in seen:
                continue
            seen.add(resolved)
            summary = json.loads(summary_path.read_text())
            summary.setdefault("algorithm", "es_td3_buffers")  # runs written before the harness existed
            summary.setdefault("final_return", summary.get("final_es_mean_return"))
            runs.append({"summary": summary, "metrics": read_metrics(metrics_path), "dir": summary_path.parent})
    return runs


def table_groups(runs: list[dict]) -> dict[tuple[str, str, str], list[dict]]:
    """The summaries of each table row, keyed ``(env, algorithm, ratio)``; ES-TD3 runs also give a
    row ``<algorithm>/td3_actor`` whose ``final_return`` is their TD3 actor's."""
    groups: dict[tuple[str, str, str], list[dict]] = defaultdict(list)
    for run in runs:
        summary, ratio = run["summary"], ratio_text(run["summary"])
        groups[(summary["env"], summary["algorithm"], ratio)].append(summary)
        if "final_td3_actor_return" in summary:
            actor = {**summary, "final_return": summary["final_td3_actor_return"]}
            groups[(summary["env"], summary["algorithm"] + TD3_ACTOR_SUFFIX, ratio)].append(actor)
    return groups


def row_order(key: tuple[str, str]) -> tuple:
    """Sort key of an (algorithm, ratio) row: ES-TD3Buffers at the paper's ratio first, then the
    other ES-TD3 variants, the baselines, other ratios; each TD3-actor row after its row."""
    algorithm, ratio = key
    base = algorithm.partition(TD3_ACTOR_SUFFIX)[0]
    rank = ROW_ORDER.index(base) if base in ROW_ORDER else len(ROW_ORDER)
    return (ratio not in ("", PAPER_RATIO), rank, ratio, algorithm)


def independent_rows(groups, env: str) -> list[tuple[str, str]]:
    """The rows of ``env`` whose runs are their own (the TD3-actor rows reuse their row's runs)."""
    return sorted(((a, r) for e, a, r in groups if e == env and TD3_ACTOR_SUFFIX not in a), key=row_order)


def is_es_td3(algorithm: str) -> bool:
    """An ES-TD3 row (three buffers or one, hard or soft overwrite): it returns its ES mean, which
    its TD3 actor can overwrite."""
    return algorithm.startswith("es_td3")


def write_csv(path: Path, columns, rows: list[dict]) -> None:
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)


def number_text(value: float, digits: int) -> str:
    """A table cell: the value, or n/a where one run gives none (NaN)."""
    return "n/a" if math.isnan(value) else f"{value:.{digits}f}"


def ci_text(low: float, high: float, digits: int) -> str:
    return "n/a" if math.isnan(low) else f"[{number_text(low, digits)}, {number_text(high, digits)}]"


def frames_text(value: float, _=None) -> str:
    """A frame count: 40k, 2.4M, 109.8M."""
    for scale, suffix in ((1e6, "M"), (1e3, "k")):
        if abs(value) >= scale:
            return f"{round(value / scale, 2):g}{suffix}"
    return f"{value:g}"
