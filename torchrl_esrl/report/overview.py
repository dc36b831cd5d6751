"""The page's first table: the paper's Table 1 for its four tasks beside what our records hold, per
budget (``experiment`` in each run's ``summary.json``). A cell without a record says ``running``
(listed in a file of started runs) or ``not run``; it never holds a number. Its rows: the paper's
and every recorded algorithm, in the order given, then by the report's row order (the recipes'
``ALGORITHMS``), Table 1's rows without a recipe here last."""
from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np

from torchrl_esrl.report.records import PAPER_RATIO, Algorithms, ci_text, frames_text, ratio_text, write_csv
from torchrl_esrl.report.statistics import interquartile_mean, iqm_confidence_interval

PAPER_TABLE_COLUMNS = ("env", "task", "algorithm", "label", "mean", "std", "median")


def read_paper_table(path) -> dict:
    """A paper's results table (``docs/results/paper_table1.csv``: the paper's Table 1 as printed):
    ``#`` lines first, its caption, then one ``env,task,algorithm,label,mean,std,median`` row per
    entry. Returns ``{"caption": text, "scores": env id -> algorithm -> (mean, std, median),
    "tasks": env id -> the paper's name of it, "labels": algorithm -> the paper's name of the row}``,
    in the file's order; a label is shown where no recipe declares the algorithm."""
    import csv

    lines = Path(path).read_text().splitlines()
    caption = " ".join(line.lstrip("#").strip() for line in lines if line.startswith("#"))
    reader = csv.DictReader(line for line in lines if line and not line.startswith("#"))
    if tuple(reader.fieldnames or ()) != PAPER_TABLE_COLUMNS:
        raise ValueError(f"{path}: columns {reader.fieldnames} (allowed: {','.join(PAPER_TABLE_COLUMNS)})")
    table: dict = {"caption": caption, "scores": {}, "tasks": {}, "labels": {}}
    for row in reader:
        scores = tuple(int(row[key]) if row[key].lstrip("-").isdigit() else float(row[key]) for key in ("mean", "std", "median"))
        table["scores"].setdefault(row["env"], {})[row["algorithm"]] = scores
        table["tasks"][row["env"]], table["labels"][row["algorithm"]] = row["task"], row["label"]
    return table


OVERVIEW_COLUMNS = ("env", "algorithm", "experiment", "runs", "seeds", "td3_frames", "es_frames", "mean", "std", "median", "iqm", "iqm_ci_low", "iqm_ci_high", "status")


def read_started(path) -> set[tuple[str, str, str]]:
    """``(env id, algorithm, experiment)`` of each started run, one per line (``#`` comments)."""
    if path is None or not Path(path).exists():
        return set()
    lines = (line.split("#")[0].split() for line in Path(path).read_text().splitlines())
    return {tuple(fields) for fields in lines if len(fields) == 3}


def _budget(summaries: list[dict]) -> str:
    td3, es = np.mean([s.get("td3_frames", 0) for s in summaries]), np.mean([s.get("es_frames", 0) for s in summaries])
    parts = [f"{frames_text(td3)} TD3" if td3 else "", f"{frames_text(es)} ES" if es else ""]
    return " + ".join(p for p in parts if p) + " frames" + (" (mean over runs)" if len(summaries) > 1 and len({s.get("es_frames") for s in summaries}) > 1 else "")


def without_recipe(paper: dict, algorithms: Algorithms) -> list[str]:
    """The paper's rows that no recipe here declares, in the table's order."""
    return [a for a in paper["labels"] if a not in algorithms.infos]


def overview_algorithms(runs: list[dict], algorithms: Algorithms, paper: dict, order=(), started=frozenset()) -> list[str]:
    """The overview's rows: the names in ``order``, then the other algorithms of the paper's table,
    of the runs and of ``started`` by the report's row order, then the paper's rows without a recipe here."""
    named = {run["summary"]["algorithm"] for run in runs} | {key[1] for key in started} | set(paper["labels"])
    missing = without_recipe(paper, algorithms)
    recipes = sorted(named - set(order) - set(missing), key=lambda a: algorithms.row_order((a, "")))
    return list(order) + recipes + [a for a in missing if a not in order]


def overview_rows(runs: list[dict], algorithms: Algorithms, paper: dict, started=frozenset(), order=()) -> tuple[list[dict], list[str]]:
    """One row per (task, algorithm, experiment) (:func:`overview_algorithms`): the statistics of
    the recorded runs at the paper's ratio (or of none: ``status`` ``running`` or ``not run``).
    Returns the rows and the experiments, the paper's first."""
    groups: dict[tuple[str, str, str], list[dict]] = defaultdict(list)
    for run in runs:
        s = run["summary"]
        if ratio_text(s) in ("", PAPER_RATIO):
            groups[(s["env"], s["algorithm"], s.get("experiment", "?"))].append(s)
    experiments = sorted({key[2] for key in groups} | {key[2] for key in started}, key=lambda e: (e != "paper", e))
    rows = []
    for env in paper["scores"]:
        for algorithm in overview_algorithms(runs, algorithms, paper, order, started):
            for experiment in experiments:
                summaries = sorted(groups.get((env, algorithm, experiment), []), key=lambda s: s["seed"])
                row = {"env": env, "algorithm": algorithm, "experiment": experiment, "runs": len(summaries), "seeds": " ".join(str(s["seed"]) for s in summaries)}
                if summaries:
                    finals = np.array([s["final_return"] for s in summaries], dtype=float)
                    low, high = iqm_confidence_interval(finals)
                    row.update(td3_frames=int(np.mean([s.get("td3_frames", 0) for s in summaries])), es_frames=int(np.mean([s.get("es_frames", 0) for s in summaries])),
                               mean=float(finals.mean()), std=float(finals.std(ddof=1)) if len(finals) > 1 else float("nan"), median=float(np.median(finals)),
                               iqm=interquartile_mean(finals), iqm_ci_low=low, iqm_ci_high=high, status="recorded", budget=_budget(summaries))
                else:
                    row["status"] = "running" if (env, algorithm, experiment) in started else "not run"
                rows.append(row)
    return rows, experiments


def _cell(row: dict) -> str:
    if row["status"] != "recorded":
        return row["status"]
    if row["runs"] == 1:
        return f"{row['mean']:.1f}: one run (seed {row['seeds']}), {row['budget']}"
    return (f"IQM {row['iqm']:.1f} {ci_text(row['iqm_ci_low'], row['iqm_ci_high'], 1)}, mean {row['mean']:.1f} (std {row['std']:.1f}); "
            f"{row['runs']} runs, {row['budget']}")


def write_overview(runs: list[dict], out_dir: Path, algorithms: Algorithms, paper: dict, started=frozenset(), order=()) -> tuple[Path, Path]:
    """``overview.csv`` and ``overview.md``: :func:`overview_rows` beside the paper's table
    (:func:`read_paper_table`), its tasks in its order; a row with a ratio is labelled with the paper's."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows, experiments = overview_rows(runs, algorithms, paper, started, order)
    with_ratio = {run["summary"]["algorithm"] for run in runs if ratio_text(run["summary"])} | {algorithms.reference}
    missing = set(without_recipe(paper, algorithms))
    csv_path, md_path = out_dir / "overview.csv", out_dir / "overview.md"
    write_csv(csv_path, OVERVIEW_COLUMNS, [{key: r.get(key, "") for key in OVERVIEW_COLUMNS} for r in rows])
    cells = {(r["env"], r["algorithm"], r["experiment"]): r for r in rows}
    recorded = {key[1] for key, cell in cells.items() if cell["status"] == "recorded"}
    with_recipe = [algorithm for algorithm in overview_algorithms(runs, algorithms, paper, order, started) if algorithm not in missing]
    lines = ["| task | row | paper, Table 1: mean (std, median) | " + " | ".join(f"ours, `experiment={e}`" for e in experiments) + " |",
             "|---|---|---|" + "---|" * len(experiments)]
    for env, entries in paper["scores"].items():
        for algorithm in overview_algorithms(runs, algorithms, paper, order, started):
            ours = [cells[(env, algorithm, e)] for e in experiments]
            if algorithm not in entries and all(r["status"] != "recorded" for r in ours):
                continue
            name = paper["labels"][algorithm] if algorithm in missing else algorithms.label(algorithm, PAPER_RATIO if algorithm in with_ratio else "")
            paper_cell = "{} (std {}, median {})".format(*entries[algorithm]) if algorithm in entries else "not in Table 1"
            ours_cells = [_cell(r) if algorithm not in missing else "no recipe here" for r in ours]
            lines.append(f"| {env} ({paper['tasks'][env]}) | {name} | {paper_cell} | " + " | ".join(ours_cells) + " |")
    lines += [
        "",
        f"Paper: {paper['caption']}",
        f"Ours: the final return of the returned policy ({algorithms.returned_text(with_recipe)}) over 10 deterministic",
        "episodes, v5 tasks, per `experiment` preset; each cell says how many runs it holds and their frames"
        + (f" ({frames})" if (frames := algorithms.frames_text(recorded)) else "") + ". One run is a run,",
        "not a statistic. IQM CI: 95% percentile bootstrap, exact over every resample of the runs. `running`: started, no",
        "record yet; `not run`: no record and not started; a cell without a record holds no number.",
    ]
    md_path.write_text("\n".join(lines) + "\n")
    return csv_path, md_path
