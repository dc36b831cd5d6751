"""The report over run directories (``recipes/report.py``): Table 1 of the paper, learning curves,
ES-vs-TD3 curves with overwrite events, and a ratio sweep.

A *run* is a directory holding ``summary.json`` and ``metrics.csv`` as written by
:class:`torchrl_esrl.run.harness.RunHarness`; any directory above runs (a Hydra multirun, a folder of
runs) is searched recursively.

- Table: per env x algorithm, the final return of the returned policy (``final_return``) over
  seeds: mean, std (ddof=1), median (the paper's Table 1) and the interquartile mean with a 95%
  stratified-bootstrap confidence interval over seeds (Agarwal et al. 2021, with their
  ``rliable`` library; one task per env, so the strata are the env's runs).
- Improvement table: per env, the probability that ES-TD3Buffers (paper ratio) beats each other
  row on a run drawn at random from each (``rliable``'s probability of improvement, a
  Mann-Whitney statistic), with its 95% stratified-bootstrap CI.
- Learning curves: ``eval_return`` against TD3 frames, mean over seeds, min-max band shaded.
  OpenAI-ES has no TD3 frames; its checkpoints are drawn at the TD3 frames ES-TD3Buffers has
  at the same iteration (``(iteration + 1) x frames_per_iteration``).
"""
from __future__ import annotations

import csv
import json
import math
from collections import defaultdict
from pathlib import Path

import warnings

import numpy as np

from torchrl_esrl.run.metrics import read_metrics

TABLE_COLUMNS = ("env", "algorithm", "ratio", "runs", "td3_frames", "es_frames", "mean", "std", "median", "iqm", "iqm_ci_low", "iqm_ci_high")
ALGORITHM_LABELS = {
    "es_td3_buffers": "ES-TD3Buffers",
    "es_td3_shared": "ES-TD3 (one shared buffer)",
    "td3": "TD3",
    "es": "OpenAI-ES",
    "cem_rl": "CEM-RL",
    "es_td3_buffers_soft": "ES-TD3Buffers (soft overwrite)",
    "es_td3_shared_soft": "ES-TD3 (one shared buffer, soft overwrite)",
}
ES_TD3_BUFFERS = ("es_td3_buffers", "es_td3_buffers_soft")  # runs that have a good:bad:noisy ratio
# ES-TD3 returns its ES mean, but the buffers act on its TD3 actor: the table and the curves also
# show that actor (``final_td3_actor_return`` / ``td3_eval_return``) as a row of its own.
TD3_ACTOR_SUFFIX = "/td3_actor"
PAPER_RATIO = "0.5:0.2:0.3"  # the curves show ES-TD3Buffers at this ratio when runs tie


def _seeds(count: int) -> str:
    return f"{count} seed" + ("s" if count != 1 else "")


def ratio_text(summary: dict) -> str:
    """``"0.5:0.2:0.3"`` for ES-TD3Buffers runs (runs at different ratios are different
    configurations: never pooled), ``""`` for every other algorithm."""
    if summary["algorithm"] not in ES_TD3_BUFFERS or summary.get("ratio") is None:
        return ""
    return ":".join(f"{float(r):g}" for r in summary["ratio"])


def label(algorithm: str, ratio: str = "") -> str:
    """Display name: ``ES-TD3Buffers 0.5:0.2:0.3: its TD3 actor`` for ``es_td3_buffers/td3_actor``."""
    base, actor, _ = algorithm.partition(TD3_ACTOR_SUFFIX)
    text = ALGORITHM_LABELS.get(base, base) + (f" {ratio}" if ratio else "")
    return text + (": its TD3 actor" if actor else "")


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


BOOTSTRAP_REPS = 2000  # rliable's default is 50,000; 2,000 keeps a report under a minute and the CI ends stable to ~1%


def _rliable():
    from rliable import library, metrics

    return library, metrics


def _interval(score_dict: dict, statistic, seed: int):
    """rliable's stratified-bootstrap point estimate and 95% percentile CI of ``statistic``."""
    library, _ = _rliable()
    with warnings.catch_warnings():  # arch (under rliable) warns that RandomState is deprecated
        warnings.simplefilter("ignore", FutureWarning)
        points, intervals = library.get_interval_estimates(score_dict, statistic, reps=BOOTSTRAP_REPS, random_state=np.random.RandomState(seed))
    (key,) = score_dict
    return float(np.ravel(points[key])[0]), float(np.ravel(intervals[key])[0]), float(np.ravel(intervals[key])[-1])


def interquartile_mean(values) -> float:
    """Mean of the middle 50% of the runs (rliable's ``aggregate_iqm``)."""
    _, metrics = _rliable()
    return float(metrics.aggregate_iqm(np.asarray(values, dtype=float).reshape(-1, 1)))


def iqm_confidence_interval(values, seed: int = 0) -> tuple[float, float]:
    """95% stratified-bootstrap CI of the IQM over runs (NaN with fewer than 2 distinct values)."""
    values = np.asarray(values, dtype=float).reshape(-1, 1)
    if values.size < 2 or np.unique(values).size < 2:
        return math.nan, math.nan
    _, metrics = _rliable()
    _, low, high = _interval({"runs": values}, lambda scores: np.array([metrics.aggregate_iqm(scores)]), seed)
    return low, high


def probability_of_improvement(x, y, seed: int = 0) -> tuple[float, float, float]:
    """P(X > Y) for a run of X and a run of Y drawn at random (ties count half), with its 95%
    stratified-bootstrap CI (rliable). NaN CI with fewer than 2 runs on either side."""
    x, y = (np.asarray(v, dtype=float).reshape(-1, 1) for v in (x, y))
    _, metrics = _rliable()
    point = float(metrics.probability_of_improvement(x, y))
    if len(x) < 2 or len(y) < 2:
        return point, math.nan, math.nan
    _, low, high = _interval({"x,y": (x, y)}, metrics.probability_of_improvement, seed)
    return point, low, high


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


def results_table(runs: list[dict]) -> list[dict]:
    """One row per (env, algorithm, ratio): statistics of ``final_return`` over its runs (and the
    TD3-actor rows of :func:`table_groups`)."""
    rows = []
    for (env, algorithm, ratio), summaries in sorted(table_groups(runs).items()):
        finals = np.array([s["final_return"] for s in summaries], dtype=float)
        low, high = iqm_confidence_interval(finals)
        rows.append(
            {
                "env": env,
                "algorithm": algorithm,
                "ratio": ratio,
                "runs": len(finals),
                "td3_frames": int(np.mean([s.get("td3_frames", 0) for s in summaries])),
                "es_frames": int(np.mean([s.get("es_frames", 0) for s in summaries])),
                "mean": float(finals.mean()),
                "std": float(finals.std(ddof=1)) if len(finals) > 1 else 0.0,
                "median": float(np.median(finals)),
                "iqm": interquartile_mean(finals),
                "iqm_ci_low": low,
                "iqm_ci_high": high,
            }
        )
    return rows


def _write_csv(path: Path, columns, rows: list[dict]) -> None:
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)


def _ci_text(low: float, high: float, digits: int) -> str:
    return "n/a" if math.isnan(low) else f"[{low:.{digits}f}, {high:.{digits}f}]"


def write_table(rows: list[dict], out_dir: Path) -> tuple[Path, Path]:
    """``results.csv`` and ``results.md`` (Table 1 layout: env x algorithm, mean / std / median)."""
    csv_path, md_path = out_dir / "results.csv", out_dir / "results.md"
    _write_csv(csv_path, TABLE_COLUMNS, rows)
    lines = [
        "| env | algorithm | runs | TD3 frames | ES frames | mean | std | median | IQM [95% CI] |",
        "|---|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        ci = _ci_text(r["iqm_ci_low"], r["iqm_ci_high"], 1)
        lines.append(f"| {r['env']} | {label(r['algorithm'], r['ratio'])} | {r['runs']} | {r['td3_frames']} | {r['es_frames']} | {r['mean']:.1f} | {r['std']:.1f} | {r['median']:.1f} | {r['iqm']:.1f} {ci} |")
    lines += [
        "",
        "Final return: deterministic evaluation of the policy each algorithm returns (ES-TD3: the ES mean;",
        "its TD3 actor on the `: its TD3 actor` rows). TD3 frames (gradient-based learner's environment",
        "steps) and ES frames (evolution's evaluation episodes) are counted separately: ES-TD3 variants",
        "spend both, so at equal TD3 frames they have used many more environment frames in total.",
    ]
    md_path.write_text("\n".join(lines) + "\n")
    return csv_path, md_path


IMPROVEMENT_COLUMNS = ("env", "algorithm", "ratio", "other_algorithm", "other_ratio", "runs", "other_runs", "probability", "ci_low", "ci_high")


def improvement_table(runs: list[dict], reference: tuple[str, str] = ("es_td3_buffers", PAPER_RATIO)) -> list[dict]:
    """Per env: probability of improvement of ``reference`` (algorithm, ratio) over every other
    row of the results table, with its 95% stratified-bootstrap CI (rliable). Envs without
    reference runs give no rows."""
    groups = table_groups(runs)
    rows = []
    for env in sorted({key[0] for key in groups}):
        mine = groups.get((env, *reference))
        if not mine:
            continue
        x = [s["final_return"] for s in mine]
        for (other_env, algorithm, ratio), summaries in sorted(groups.items()):
            if other_env != env or (algorithm, ratio) == reference:
                continue
            y = [s["final_return"] for s in summaries]
            probability, low, high = probability_of_improvement(x, y)
            rows.append({"env": env, "algorithm": reference[0], "ratio": reference[1], "other_algorithm": algorithm, "other_ratio": ratio, "runs": len(x), "other_runs": len(y), "probability": probability, "ci_low": low, "ci_high": high})
    return rows


def write_improvement_table(rows: list[dict], out_dir: Path) -> tuple[Path, Path]:
    """``improvement.csv`` and ``improvement.md``: P(ES-TD3Buffers > row) per env, with CI."""
    csv_path, md_path = out_dir / "improvement.csv", out_dir / "improvement.md"
    _write_csv(csv_path, IMPROVEMENT_COLUMNS, rows)
    lines = ["| env | P(ES-TD3Buffers > row) | row | runs (ES-TD3Buffers / row) | 95% CI |", "|---|---:|---|---|---|"]
    for r in rows:
        ci = _ci_text(r["ci_low"], r["ci_high"], 2)
        lines.append(f"| {r['env']} | {r['probability']:.2f} | {label(r['other_algorithm'], r['other_ratio'])} | {r['runs']} / {r['other_runs']} | {ci} |")
    lines += [
        "",
        f"Probability of improvement (Agarwal et al. 2021, rliable): the chance that a run of ES-TD3Buffers {PAPER_RATIO}",
        "ends with a higher final return than a run of the row, ties counting half; 0.5 = no difference.",
        "A CI that excludes 0.5 is a difference at the 95% level. CIs: stratified bootstrap over runs.",
    ]
    md_path.write_text("\n".join(lines) + "\n")
    return csv_path, md_path


RUN_COLUMNS = ("env", "algorithm", "ratio", "seed", "final_return", "final_td3_actor_return", "overwrites", "td3_frames", "es_frames",
               "td3_updates", "first_td3_update", "wall_time_s", "dir")


def first_td3_update(metrics: list[dict]) -> int | str:
    """The iteration (from 1) whose row first counts TD3 updates: when TD3 started learning,
    which in ES-TD3Buffers waits for every buffer to hold K (Algorithm 1). ``"never"`` when no
    row counts one; ``""`` for a run that logs no ``td3_updates``."""
    if not metrics or "td3_updates" not in metrics[0]:
        return ""
    return next((i + 1 for i, row in enumerate(metrics) if row["td3_updates"]), "never")


def write_runs_table(runs: list[dict], out_dir: Path) -> tuple[Path, Path]:
    """``runs.csv`` and ``runs.md``: one row per run (seed), the numbers behind each table row."""
    rows = []
    for run in runs:
        s = run["summary"]
        rows.append({**{key: s.get(key, "") for key in RUN_COLUMNS}, "ratio": ratio_text(s), "dir": str(run["dir"]),
                     "first_td3_update": first_td3_update(run["metrics"])})
    rows.sort(key=lambda r: (r["env"], r["algorithm"], r["ratio"], r["seed"]))
    csv_path, md_path = out_dir / "runs.csv", out_dir / "runs.md"
    _write_csv(csv_path, RUN_COLUMNS, rows)

    def number(value, digits=1):
        return f"{value:.{digits}f}" if isinstance(value, (int, float)) else "-"

    lines = [
        "| env | algorithm | seed | final return | TD3 actor | overwrites | TD3 frames | ES frames | TD3 updates | first TD3 update (iteration) | wall time (min) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        overwrites = r["overwrites"] if r["overwrites"] != "" else "-"
        wall = number(r["wall_time_s"] / 60 if isinstance(r["wall_time_s"], (int, float)) else None)
        lines.append(
            f"| {r['env']} | {label(r['algorithm'], r['ratio'])} | {r['seed']} | {number(r['final_return'])} | "
            f"{number(r['final_td3_actor_return'])} | {overwrites} | {r['td3_frames']} | {r['es_frames']} | "
            f"{r['td3_updates'] if r['td3_updates'] != '' else '-'} | {r['first_td3_update'] or '-'} | {wall} |"
        )
    md_path.write_text("\n".join(lines) + "\n")
    return csv_path, md_path


def _curve_x(run: dict) -> np.ndarray:
    frames = np.array([row["td3_frames"] for row in run["metrics"]], dtype=float)
    if frames.any():
        return frames
    per_iteration = run["summary"].get("frames_per_iteration", 1)
    return np.array([(row["iteration"] + 1) * per_iteration for row in run["metrics"]], dtype=float)



def _pyplot():
    """matplotlib's pyplot on the file-only Agg backend (reports run headless)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    _pyplot().close(fig)
    return path

def plot_learning_curves(runs: list[dict], out_dir: Path) -> list[Path]:
    """One PNG per env: eval return vs TD3 frames, one line per algorithm, seeds' min-max shaded;
    ES-TD3 variants also draw their TD3 actor's mean as a dashed line. Of ES-TD3Buffers, only the
    ratio with the most runs is drawn (a ratio sweep has its own figure, ``plot_ratio_sweep``)."""
    plt = _pyplot()

    paths = []
    by_env: dict[str, dict[tuple[str, str], list[dict]]] = defaultdict(lambda: defaultdict(list))
    for run in runs:
        by_env[run["summary"]["env"]][(run["summary"]["algorithm"], ratio_text(run["summary"]))].append(run)
    for env, by_config in sorted(by_env.items()):
        ratios = [(len(group), ratio == PAPER_RATIO, ratio) for (algorithm, ratio), group in by_config.items() if ratio]
        main_ratio = max(ratios)[-1] if ratios else ""
        fig, ax = plt.subplots(figsize=(7, 4.5))
        for (algorithm, ratio), group in sorted(by_config.items()):
            if ratio != main_ratio and ratio:
                continue
            length = min(len(run["metrics"]) for run in group)
            x = _curve_x(group[0])[:length]
            returns = np.array([[row["eval_return"] for row in run["metrics"][:length]] for run in group], dtype=float)
            (line,) = ax.plot(x, returns.mean(axis=0), marker="o", markersize=3, label=f"{label(algorithm, ratio)} ({_seeds(len(group))})")
            if len(group) > 1:
                ax.fill_between(x, returns.min(axis=0), returns.max(axis=0), color=line.get_color(), alpha=0.2)
            if all("td3_eval_return" in run["metrics"][0] for run in group):  # ES-TD3: its TD3 actor, dashed
                actor = np.array([[row["td3_eval_return"] for row in run["metrics"][:length]] for run in group], dtype=float)
                ax.plot(x, actor.mean(axis=0), linestyle="--", color=line.get_color(), alpha=0.8, label=label(algorithm + TD3_ACTOR_SUFFIX, ratio))
        ax.set_xlabel("TD3 frames (OpenAI-ES: at the same iteration checkpoints)")
        ax.set_ylabel("evaluation return (deterministic)")
        ax.set_title(f"{env}: returned policy, mean over seeds (band: min-max)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
        paths.append(_save(fig, out_dir / f"curves_{env}.png"))
    return paths


# What each algorithm returns, for the per-run figure when its metrics have no TD3/ES columns.
RETURNED_POLICY = {"td3": "TD3 actor", "es": "ES mean", "cem_rl": "CEM mean"}


def _draw_es_vs_td3(ax, run: dict) -> None:
    """One run's panel: TD3 actor and ES mean per iteration (ES-TD3 runs; other algorithms: the
    returned policy), the initial policy's return if recorded, overwrites as red dashed lines."""
    from matplotlib.ticker import MaxNLocator

    rows, summary = run["metrics"], run["summary"]
    iterations = [row["iteration"] for row in rows]
    if "td3_eval_return" in rows[0]:
        ax.plot(iterations, [row["td3_eval_return"] for row in rows], marker="o", markersize=3, label="TD3 actor")
        ax.plot(iterations, [row["es_eval_return"] for row in rows], marker="s", markersize=3, label="ES mean")
    else:
        name = RETURNED_POLICY.get(summary["algorithm"], "returned policy")
        ax.plot(iterations, [row["eval_return"] for row in rows], marker="o", markersize=3, label=name)
    if summary.get("initial_return") is not None:
        ax.axhline(summary["initial_return"], color="grey", linestyle=":", label="initial policy")
    overwritten = [row["iteration"] for row in rows if row.get("overwritten") is True]
    for i, it in enumerate(overwritten):
        ax.axvline(it, color="red", linestyle="--", alpha=0.6, label="ES mean overwritten" if i == 0 else None)
    ax.set_xlabel("iteration")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.grid(alpha=0.3)


def plot_run(run_dir, summary: dict | None = None) -> Path:
    """``learning_curve.png`` in one run directory (every recipe, at the end of its run, before
    ``summary`` is written; by default read from ``summary.json``): the deterministic evaluations
    per iteration as in :func:`plot_es_vs_td3`, overwrites marked."""
    plt = _pyplot()
    run_dir = Path(run_dir)
    summary = summary if summary is not None else json.loads((run_dir / "summary.json").read_text())
    run = {"summary": summary, "metrics": read_metrics(run_dir / "metrics.csv"), "dir": run_dir}
    fig, ax = plt.subplots(figsize=(6, 4))
    _draw_es_vs_td3(ax, run)
    ax.set_ylabel("evaluation return (deterministic)")
    ax.set_title(f"{summary['env']}, seed {summary['seed']}: {label(summary['algorithm'], ratio_text(summary))}", fontsize=10)
    ax.legend(fontsize=8, loc="best")
    return _save(fig, run_dir / "learning_curve.png")


def plot_es_vs_td3(runs: list[dict], out_dir: Path) -> list[Path]:
    """Per env, ES-TD3Buffers' TD3 actor vs ES mean per iteration, one panel per run; overwrites marked."""
    plt = _pyplot()

    paths = []
    by_env: dict[str, list[dict]] = defaultdict(list)
    for run in runs:
        if run["summary"]["algorithm"] in ES_TD3_BUFFERS and run["metrics"] and "td3_eval_return" in run["metrics"][0]:
            by_env[run["summary"]["env"]].append(run)
    for env, group in sorted(by_env.items()):
        group = sorted(group, key=lambda r: (r["summary"]["algorithm"], ratio_text(r["summary"]), r["summary"]["seed"]))
        fig, axes = plt.subplots(1, len(group), figsize=(4 * len(group), 3.6), squeeze=False, sharey=True)
        for ax, run in zip(axes[0], group):
            _draw_es_vs_td3(ax, run)
            soft = ", soft overwrite" if run["summary"]["algorithm"].endswith("_soft") else ""
            ax.set_title(f"seed {run['summary']['seed']}, ratio {ratio_text(run['summary'])}{soft}", fontsize=9)
        axes[0][0].set_ylabel("evaluation return")
        handles, labels = [], []
        for ax in axes[0]:
            for h, lab in zip(*ax.get_legend_handles_labels()):
                if lab not in labels:
                    handles.append(h)
                    labels.append(lab)
        axes[0][0].legend(handles, labels, fontsize=8, loc="best")
        fig.suptitle(f"{env}: ES-TD3Buffers, TD3 vs ES per iteration", fontsize=10)
        paths.append(_save(fig, out_dir / f"es_vs_td3_{env}.png"))
    return paths


def plot_ratio_sweep(runs: list[dict], out_dir: Path) -> list[Path]:
    """Per env with ES-TD3Buffers runs at 2+ ratios: final return vs ratio, of the returned ES mean
    and of the TD3 actor (the policy the ratio acts on directly): mean ± std, seeds as dots."""
    plt = _pyplot()

    paths = []
    by_env: dict[str, dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for run in runs:
        if run["summary"]["algorithm"] == "es_td3_buffers" and ratio_text(run["summary"]):  # the hard overwrite of Algorithm 1
            by_env[run["summary"]["env"]][ratio_text(run["summary"])].append(run["summary"])
    series = (("final_return", "ES mean (returned)", "o", -0.12), ("final_td3_actor_return", "TD3 actor", "s", 0.12))
    for env, by_ratio in sorted(by_env.items()):
        if len(by_ratio) < 2:
            continue
        ratios = sorted(by_ratio)
        fig, ax = plt.subplots(figsize=(max(5.5, 1.6 * len(ratios)), 4))
        for color, (key, name, marker, shift) in enumerate(series):
            for i, ratio in enumerate(ratios):
                values = np.array([s[key] for s in by_ratio[ratio] if key in s], dtype=float)
                if not len(values):
                    continue
                std = values.std(ddof=1) if len(values) > 1 else 0.0
                ax.errorbar(i + shift, values.mean(), yerr=std, fmt=marker, capsize=4, color=f"C{color}", label=name if i == 0 else None)
                ax.scatter(np.full(len(values), i + shift + 0.05), values, s=10, color=f"C{color}", alpha=0.5)
        ax.set_xticks(range(len(ratios)), [f"{r}\n({_seeds(len(by_ratio[r]))})" for r in ratios], fontsize=8)
        ax.set_xlabel("buffer ratio good:bad:noisy")
        ax.set_ylabel("final evaluation return")
        ax.set_title(f"{env}: ratio sweep (mean ± std; dots: seeds)", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
        paths.append(_save(fig, out_dir / f"ratio_sweep_{env}.png"))
    return paths


def plot_hard_vs_soft(runs: list[dict], out_dir: Path) -> list[Path]:
    """Per env with both: ES-TD3Buffers with the hard overwrite (Algorithm 1) against the soft one
    (Section 5). Left: the returned policy's evaluation return, mean over seeds with the seeds'
    min-max band (the variance the soft overwrite is meant to reduce); right: final return per
    seed, with the number of overwrites each run made next to its dot."""
    plt = _pyplot()

    paths = []
    by_env: dict[str, dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for run in runs:
        s = run["summary"]
        if s["algorithm"] in ES_TD3_BUFFERS and ratio_text(s) == PAPER_RATIO and run["metrics"]:
            by_env[s["env"]][s["algorithm"]].append(run)
    for env, by_mode in sorted(by_env.items()):
        if len(by_mode) < 2:
            continue
        fig, (curves, finals) = plt.subplots(1, 2, figsize=(11, 4), gridspec_kw={"width_ratios": [2, 1]})
        for i, algorithm in enumerate(ES_TD3_BUFFERS):
            group = by_mode[algorithm]
            length = min(len(run["metrics"]) for run in group)
            x = _curve_x(group[0])[:length]
            returns = np.array([[row["eval_return"] for row in run["metrics"][:length]] for run in group], dtype=float)
            name = f"{label(algorithm)} ({_seeds(len(group))})"
            curves.plot(x, returns.mean(axis=0), marker="o", markersize=3, color=f"C{i}", label=name)
            curves.fill_between(x, returns.min(axis=0), returns.max(axis=0), color=f"C{i}", alpha=0.2)
            values = [run["summary"]["final_return"] for run in group]
            finals.scatter(np.full(len(values), i), values, color=f"C{i}", s=18)
            for value, run in zip(values, group):
                finals.annotate(str(run["summary"].get("overwrites", "")), (i, value), textcoords="offset points", xytext=(6, -3), fontsize=7)
            finals.hlines(interquartile_mean(values), i - 0.2, i + 0.2, color=f"C{i}")
        curves.set_xlabel("TD3 frames")
        curves.set_ylabel("evaluation return (returned ES mean)")
        curves.grid(alpha=0.3)
        curves.legend(fontsize=8, loc="best")
        finals.set_xticks(range(len(ES_TD3_BUFFERS)), ["hard", "soft"])
        finals.set_xlim(-0.6, len(ES_TD3_BUFFERS) - 0.4)
        finals.set_ylabel("final return (line: IQM; numbers: overwrites)")
        finals.grid(alpha=0.3)
        fig.suptitle(f"{env}: hard vs soft overwrite, ES-TD3Buffers {PAPER_RATIO} (band: seeds' min-max)", fontsize=10)
        paths.append(_save(fig, out_dir / f"hard_vs_soft_{env}.png"))
    return paths


def make_report(paths, out_dir) -> dict:
    """Everything: the table (csv + md) and the PNGs; returns what was written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    runs = find_runs(paths)
    if not runs:
        raise FileNotFoundError(f"no run (summary.json + metrics.csv) under {[str(p) for p in paths]}")
    rows = results_table(runs)
    csv_path, md_path = write_table(rows, out_dir)
    write_runs_table(runs, out_dir)
    improvement = improvement_table(runs)
    improvement_csv, improvement_md = write_improvement_table(improvement, out_dir)
    figures = plot_learning_curves(runs, out_dir) + plot_es_vs_td3(runs, out_dir) + plot_ratio_sweep(runs, out_dir) + plot_hard_vs_soft(runs, out_dir)
    return {"runs": len(runs), "rows": rows, "table_csv": csv_path, "table_md": md_path, "improvement": improvement, "improvement_csv": improvement_csv, "improvement_md": improvement_md, "figures": figures}
