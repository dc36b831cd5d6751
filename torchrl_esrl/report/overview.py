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

# es_td3buffers.tex, Table 1 ("Scores achieved on MuJoCo Environments. Baselines as reported in
# Lee et al. 2020"): (mean, std, median) per task and algorithm, as the paper prints them. The
# paper names the tasks without a version and does not say how many runs an entry summarises.
PAPER_TABLE_1 = {
    "HalfCheetah-v5": {"td3": (9630, 202, 9606), "cem": (2940, 353, 3045), "erl": (8684, 130, 8675), "cem_rl": (10725, 397, 11539), "es_td3_buffers": (10793, 778, 10862)},
    "Ant-v5": {"td3": (4027, 403, 4587), "cem": (487, 33, 506), "erl": (3716, 673, 4240), "cem_rl": (4251, 251, 4310), "es_td3_buffers": (4532, 999, 4367)},
    "Swimmer-v5": {"td3": (63, 9, 47), "cem": (351, 9, 361), "erl": (350, 8, 360), "cem_rl": (75, 11, 62), "es_td3_buffers": (213, 119, 174)},
    "Walker2d-v5": {"td3": (3808, 339, 3882), "cem": (928, 50, 934), "erl": (2188, 240, 2267), "cem_rl": (4711, 155, 4637), "es_td3_buffers": (2217, 1454, 1764)},
}
PAPER_NAMES = {"HalfCheetah-v5": "HalfCheetah", "Ant-v5": "Ant", "Swimmer-v5": "Swimmer", "Walker2d-v5": "Walker"}
PAPER_LABELS = {"cem": "CEM", "erl": "ERL"}  # Table 1's rows without a recipe here
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


def overview_algorithms(runs: list[dict], algorithms: Algorithms, order=(), started=frozenset()) -> list[str]:
    """The overview's rows: the names in ``order``, then the other algorithms of Table 1, of the
    runs and of ``started`` by the report's row order, then Table 1's rows without a recipe here."""
    named = {run["summary"]["algorithm"] for run in runs} | {key[1] for key in started} | {a for paper in PAPER_TABLE_1.values() for a in paper}
    recipes = sorted(named - set(order) - set(PAPER_LABELS), key=lambda a: algorithms.row_order((a, "")))
    return list(order) + recipes + [a for a in PAPER_LABELS if a not in order]


def overview_rows(runs: list[dict], algorithms: Algorithms, started=frozenset(), order=()) -> tuple[list[dict], list[str]]:
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
    for env in PAPER_TABLE_1:
        for algorithm in overview_algorithms(runs, algorithms, order, started):
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


def write_overview(runs: list[dict], out_dir: Path, algorithms: Algorithms, started=frozenset(), order=()) -> tuple[Path, Path]:
    """``overview.csv`` and ``overview.md``: :func:`overview_rows` beside :data:`PAPER_TABLE_1`; a
    row with a ratio is labelled with the paper's."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows, experiments = overview_rows(runs, algorithms, started, order)
    with_ratio = {run["summary"]["algorithm"] for run in runs if ratio_text(run["summary"])} | {algorithms.reference}
    csv_path, md_path = out_dir / "overview.csv", out_dir / "overview.md"
    write_csv(csv_path, OVERVIEW_COLUMNS, [{key: r.get(key, "") for key in OVERVIEW_COLUMNS} for r in rows])
    cells = {(r["env"], r["algorithm"], r["experiment"]): r for r in rows}
    lines = ["| task | row | paper, Table 1: mean (std, median) | " + " | ".join(f"ours, `experiment={e}`" for e in experiments) + " |",
             "|---|---|---|" + "---|" * len(experiments)]
    for env, paper in PAPER_TABLE_1.items():
        for algorithm in overview_algorithms(runs, algorithms, order, started):
            ours = [cells[(env, algorithm, e)] for e in experiments]
            if algorithm not in paper and all(r["status"] != "recorded" for r in ours):
                continue
            name = PAPER_LABELS.get(algorithm) or algorithms.label(algorithm, PAPER_RATIO if algorithm in with_ratio else "")
            paper_cell = "{} (std {}, median {})".format(*paper[algorithm]) if algorithm in paper else "not in Table 1"
            ours_cells = [_cell(r) if algorithm not in PAPER_LABELS else "no recipe here" for r in ours]
            lines.append(f"| {env} ({PAPER_NAMES[env]}) | {name} | {paper_cell} | " + " | ".join(ours_cells) + " |")
    lines += [
        "",
        "Paper: Table 1 of the paper as printed (ES-TD3Buffers at 20 iterations of 100k TD3 frames, 2M in all, and 50 ES",
        "generations an iteration; the baselines as reported in Lee et al. 2020); it gives no run count and names the tasks",
        "without a version. Ours: the final return of the returned policy (the ES mean for the ES rows) over 10 deterministic",
        "episodes, v5 tasks, per `experiment` preset; each cell says how many runs it holds and their frames. One run is a run,",
        "not a statistic. IQM CI: 95% percentile bootstrap, exact over every resample of the runs. `running`: started, no",
        "record yet; `not run`: no record and not started; a cell without a record holds no number.",
    ]
    md_path.write_text("\n".join(lines) + "\n")
    return csv_path, md_path
