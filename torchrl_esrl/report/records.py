"""The runs a report reads and how it groups them.

A *run* is a directory holding ``summary.json`` and ``metrics.csv`` as written by
:class:`torchrl_esrl.run.harness.RunHarness`; any directory above runs (a Hydra multirun, a folder
of runs) is searched recursively. A row of a table is an (env, algorithm, ratio): runs at different
good:bad:noisy ratios are different configurations and never pooled. The report knows no algorithm
by name: labels and row order come from the recipes' ``ALGORITHMS``, and the rows it compares
against are its parameters (:class:`Algorithms`).
"""
from __future__ import annotations

import csv
import json
import math
from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from torchrl_esrl.run.algorithm_info import AlgorithmInfo
from torchrl_esrl.run.metrics import read_metrics
from torchrl_esrl.run.plot import RETURNED_POLICY, TD3_ACTOR, TD3_ACTOR_SUFFIX, label, ratio_text  # noqa: F401  (the report's names)

PAPER_RATIO = "0.5:0.2:0.3"  # a row with a ratio is shown at this one first, and in the curves when runs tie


@dataclass(frozen=True)
class Algorithms:
    """What the report knows of the algorithms: each one's :class:`AlgorithmInfo` (the recipes'
    ``ALGORITHMS``, :func:`~torchrl_esrl.run.algorithm_info.discover`), and the rows it compares
    against. ``reference``: the row every other is compared to (probability of improvement,
    aggregate; at :data:`PAPER_RATIO` when its runs have a ratio); ``normalise_by``: the row whose
    mean final return is 1 on the normalised scale; ``es_alone``: the row whose runs a
    never-overwritten ES mean is checked against, seed by seed. A role not given is left out."""

    infos: Mapping[str, AlgorithmInfo] = field(default_factory=dict)
    reference: str | None = None
    normalise_by: str | None = None
    es_alone: str | None = None

    def info(self, algorithm: str) -> AlgorithmInfo:
        """The algorithm's info (of the row's algorithm for a TD3-actor row); a name no recipe
        declares is its own label, with the default rank."""
        base = algorithm.partition(TD3_ACTOR_SUFFIX)[0]
        return self.infos.get(base) or AlgorithmInfo(base, base, RETURNED_POLICY)

    def label(self, algorithm: str, ratio: str = "") -> str:
        return label(algorithm, ratio, self.infos)

    def row_order(self, key: tuple[str, str]) -> tuple:
        """Sort key of an (algorithm, ratio) row: the rows at no or the paper's ratio first, then by
        rank and label (the recipes' ``ALGORITHMS``), other ratios after; each TD3-actor row after its row."""
        algorithm, ratio = key
        info = self.info(algorithm)
        return (ratio not in ("", PAPER_RATIO), info.rank, info.label, ratio, algorithm)

    def grouped_labels(self, algorithms, attribute: str) -> dict[str, list[str]]:
        """The labels of ``algorithms`` (TD3-actor rows are their row's) grouped by their infos'
        ``attribute``, in row order; an empty value is left out."""
        groups: dict[str, list[str]] = {}
        for algorithm in sorted({a.partition(TD3_ACTOR_SUFFIX)[0] for a in algorithms}, key=lambda a: self.row_order((a, ""))):
            info = self.info(algorithm)
            if getattr(info, attribute):
                groups.setdefault(getattr(info, attribute), []).append(info.label)
        return groups

    def returned_text(self, algorithms) -> str:
        """What each of ``algorithms`` returns, grouped by policy in row order:
        ``"ES mean: ES-TD3Buffers, OpenAI-ES; TD3 actor: TD3"``."""
        return "; ".join(f"{policy}: {', '.join(labels)}" for policy, labels in self.grouped_labels(algorithms, "returned").items())

    def frames_text(self, algorithms) -> str:
        """What the TD3 frames of ``algorithms`` count where a recipe says they are not a TD3
        learner's own steps (``AlgorithmInfo.td3_frames``): ``"CEM-RL: every member's ..."``; empty when none says."""
        return "; ".join(f"{', '.join(labels)}: {meaning}" for meaning, labels in self.grouped_labels(algorithms, "td3_frames").items())

    def reference_row(self, keys) -> tuple[str, str] | None:
        """The (algorithm, ratio) of ``reference`` among ``keys``: at the paper's ratio or none."""
        return next((key for key in keys if key[0] == self.reference and key[1] in ("", PAPER_RATIO)), None)


def seeds_text(count: int) -> str:
    return f"{count} seed" + ("s" if count != 1 else "")


def find_runs(paths, unnamed: str = "unnamed") -> list[dict]:
    """Every run under ``paths``: its summary, its metrics rows and its directory; a summary that
    names no algorithm (written before the harness existed) is ``unnamed``'s. A run reached twice
    (overlapping paths, a symlink) counts once."""
    runs, seen = [], set()
    for root in map(Path, paths):
        for summary_path in sorted(root.rglob("summary.json")):
            metrics_path, resolved = summary_path.with_name("metrics.csv"), summary_path.resolve()
            if not metrics_path.exists() or resolved in seen:
                continue
            seen.add(resolved)
            summary = json.loads(summary_path.read_text())
            summary.setdefault("algorithm", unnamed)
            summary.setdefault("final_return", summary.get("final_es_mean_return"))
            runs.append({"summary": summary, "metrics": read_metrics(metrics_path), "dir": summary_path.parent})
    return runs


def table_groups(runs: list[dict]) -> dict[tuple[str, str, str], list[dict]]:
    """The summaries of each table row, keyed ``(env, algorithm, ratio)``; runs with a TD3 actor
    beside their returned policy (``final_td3_actor_return``) also give a row
    ``<algorithm>/td3_actor`` whose ``final_return`` is their TD3 actor's."""
    groups: dict[tuple[str, str, str], list[dict]] = defaultdict(list)
    for run in runs:
        summary, ratio = run["summary"], ratio_text(run["summary"])
        groups[(summary["env"], summary["algorithm"], ratio)].append(summary)
        if "final_td3_actor_return" in summary:
            actor = {**summary, "final_return": summary["final_td3_actor_return"]}
            groups[(summary["env"], summary["algorithm"] + TD3_ACTOR_SUFFIX, ratio)].append(actor)
    return groups


def independent_rows(groups, env: str, algorithms: Algorithms) -> list[tuple[str, str]]:
    """The rows of ``env`` whose runs are their own (the TD3-actor rows reuse their row's runs)."""
    return sorted(((a, r) for e, a, r in groups if e == env and TD3_ACTOR_SUFFIX not in a), key=algorithms.row_order)


def records_overwrites(run: dict) -> bool:
    """A run whose TD3 actor can overwrite the ES mean it returns: its summary counts
    ``overwrites`` or its metrics mark each iteration ``overwritten``."""
    return "overwrites" in run["summary"] or bool(run["metrics"]) and "overwritten" in run["metrics"][0]


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
