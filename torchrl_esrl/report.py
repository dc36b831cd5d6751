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
- Pairwise table: per env, every pair of rows: exact permutation test of the difference of mean
  final returns (scipy), Holm's correction across the env's pairs; a difference is called one
  only when the corrected p < 0.05.
- Aggregate table (2+ envs with a TD3 row): rliable's aggregate IQM and probability of
  improvement on scores normalised per env as (final - random) / (TD3 - random).
- Figures: learning curves against TD3 frames and against TD3 + ES frames (mean over seeds, 95%
  bootstrap CI of the mean; panels of at most five lines), buffer sizes per run, the TD3 actor vs
  the ES mean per run, ratio sweep, hard vs soft overwrite, the aggregate. OpenAI-ES has no TD3
  frames; on the TD3-frame axis its checkpoints are drawn at the TD3 frames ES-TD3Buffers has at
  the same iteration (``(iteration + 1) x frames_per_iteration``).
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
    """rliable's stratified-bootstrap point estimate and 95% percentile CI of ``statistic``.

    rliable 1.2's bootstraps draw their resamples from numpy's global stream (``np.random.choice``
    in ``update_indices``), not from the ``random_state`` they are given: the global stream is
    seeded with ``seed`` for the call and restored after it, so a CI is a function of its data."""
    library, _ = _rliable()
    state = np.random.get_state()
    try:
        np.random.seed(seed)
        with warnings.catch_warnings():  # arch (under rliable) warns that RandomState is deprecated
            warnings.simplefilter("ignore", FutureWarning)
            points, intervals = library.get_interval_estimates(score_dict, statistic, reps=BOOTSTRAP_REPS, random_state=np.random.RandomState(seed))
    finally:
        np.random.set_state(state)
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


EXACT_PERMUTATIONS = 1_000_000  # up to this many relabelings the permutation test enumerates them all
SIGNIFICANCE = 0.05  # a difference is called one when its Holm-corrected p is below this


def _mean_difference(x, y, axis=-1):
    return np.mean(x, axis=axis) - np.mean(y, axis=axis)


def permutation_test(x, y, seed: int = 0) -> tuple[float, int, bool]:
    """Two-sided permutation test of the difference of means of two independent samples
    (``scipy.stats.permutation_test``, ``permutation_type="independent"``). Exact, over every
    one of the C(n + m, n) relabelings, when they number at most ``EXACT_PERMUTATIONS`` (252 for
    5 vs 5); else 100,000 random relabelings. Returns (p, relabelings used, exact). scipy's
    two-sided p is twice the smaller one-sided p, capped at 1: 2/252 for two fully separated
    5-vs-5 samples. A sample of one run is not tested (scipy needs two): (NaN, 0, False)."""
    from scipy import stats

    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if len(x) < 2 or len(y) < 2:
        return math.nan, 0, False
    relabelings = math.comb(len(x) + len(y), len(x))
    exact = relabelings <= EXACT_PERMUTATIONS
    result = stats.permutation_test((x, y), _mean_difference, permutation_type="independent", vectorized=True,
                                    n_resamples=np.inf if exact else 100_000, alternative="two-sided", rng=np.random.default_rng(seed))
    return float(result.pvalue), relabelings if exact else 100_000, exact


def holm(pvalues) -> np.ndarray:
    """Holm's step-down adjusted p-values (Holm 1979): the i-th smallest of m p-values times
    (m - i + 1), made non-decreasing in that order, capped at 1. Rejecting where the adjusted p is
    below alpha controls the family-wise error rate at alpha."""
    p = np.asarray(pvalues, dtype=float)
    order = np.argsort(p, kind="stable")
    adjusted = np.minimum(1.0, np.maximum.accumulate(p[order] * (len(p) - np.arange(len(p)))))
    out = np.empty_like(adjusted)
    out[order] = adjusted
    return out


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
                "std": float(finals.std(ddof=1)) if len(finals) > 1 else math.nan,  # one run has no spread
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


def _number_text(value: float, digits: int) -> str:
    """A table cell: the value, or n/a where one run gives none (NaN)."""
    return "n/a" if math.isnan(value) else f"{value:.{digits}f}"


def _ci_text(low: float, high: float, digits: int) -> str:
    return "n/a" if math.isnan(low) else f"[{_number_text(low, digits)}, {_number_text(high, digits)}]"


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
        lines.append(f"| {r['env']} | {label(r['algorithm'], r['ratio'])} | {r['runs']} | {r['td3_frames']} | {r['es_frames']} | {r['mean']:.1f} | {_number_text(r['std'], 1)} | {r['median']:.1f} | {r['iqm']:.1f} {ci} |")
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
        "CIs: stratified bootstrap over runs. A difference is called one only by the Holm-corrected permutation",
        "tests of pairwise.md, not by a CI here.",
    ]
    md_path.write_text("\n".join(lines) + "\n")
    return csv_path, md_path


ROW_ORDER = ("es_td3_buffers", "es_td3_buffers_soft", "es_td3_shared", "es_td3_shared_soft", "td3", "cem_rl", "es")


def row_order(key: tuple[str, str]) -> tuple:
    """Sort key of an (algorithm, ratio) row: ES-TD3Buffers at the paper's ratio first, then the
    other ES-TD3 variants, the baselines, other ratios; each TD3-actor row after its row."""
    algorithm, ratio = key
    base = algorithm.partition(TD3_ACTOR_SUFFIX)[0]
    rank = ROW_ORDER.index(base) if base in ROW_ORDER else len(ROW_ORDER)
    return (ratio not in ("", PAPER_RATIO), rank, ratio, algorithm)


def _independent_rows(groups, env: str) -> list[tuple[str, str]]:
    """The rows of ``env`` whose runs are their own (the TD3-actor rows reuse their row's runs)."""
    return sorted(((a, r) for e, a, r in groups if e == env and TD3_ACTOR_SUFFIX not in a), key=row_order)


PAIRWISE_COLUMNS = ("env", "algorithm", "ratio", "other_algorithm", "other_ratio", "runs", "other_runs", "mean_difference",
                    "relabelings", "exact", "p_value", "p_holm", "difference")


def pairwise_table(runs: list[dict]) -> list[dict]:
    """Per env, every pair of rows (TD3-actor rows left out: same runs as their row): the
    permutation test of :func:`permutation_test` on the final returns, and Holm's correction
    across that env's tested pairs (a row of one run is not tested: NaN). ``difference`` is True
    only when the corrected p < ``SIGNIFICANCE``."""
    groups = table_groups(runs)
    rows = []
    for env in sorted({key[0] for key in groups}):
        keys = _independent_rows(groups, env)
        env_rows = []
        for i, first in enumerate(keys):
            for second in keys[i + 1:]:
                x = [s["final_return"] for s in groups[(env, *first)]]
                y = [s["final_return"] for s in groups[(env, *second)]]
                p_value, relabelings, exact = permutation_test(x, y)
                env_rows.append({"env": env, "algorithm": first[0], "ratio": first[1], "other_algorithm": second[0], "other_ratio": second[1],
                                 "runs": len(x), "other_runs": len(y), "mean_difference": float(np.mean(x) - np.mean(y)),
                                 "relabelings": relabelings, "exact": exact, "p_value": p_value})
        tested = [r for r in env_rows if not math.isnan(r["p_value"])]  # Holm's family: the pairs that were tested
        for row, adjusted in zip(tested, holm([r["p_value"] for r in tested]) if tested else []):
            row.update(p_holm=float(adjusted), difference=bool(adjusted < SIGNIFICANCE))
        for row in env_rows:
            row.setdefault("p_holm", math.nan)
            row.setdefault("difference", False)
        rows += env_rows
    return rows


def write_pairwise_table(rows: list[dict], out_dir: Path) -> tuple[Path, Path]:
    """``pairwise.csv`` and ``pairwise.md``: the permutation tests of :func:`pairwise_table`."""
    csv_path, md_path = out_dir / "pairwise.csv", out_dir / "pairwise.md"
    _write_csv(csv_path, PAIRWISE_COLUMNS, rows)
    lines = ["| env | row | other row | runs | mean difference | p (permutation) | p (Holm) | difference? |", "|---|---|---|---|---:|---:|---:|---|"]
    for r in rows:
        if math.isnan(r["p_value"]):
            p_text, holm_text = "not tested (one run)", "-"
        else:
            p_text, holm_text = f"{r['p_value']:.4f}" + ("" if r["exact"] else " (random relabelings)"), f"{r['p_holm']:.4f}"
        lines.append(f"| {r['env']} | {label(r['algorithm'], r['ratio'])} | {label(r['other_algorithm'], r['other_ratio'])} | {r['runs']} / {r['other_runs']} | "
                     f"{r['mean_difference']:.1f} | {p_text} | {holm_text} | {'**yes**' if r['difference'] else 'no'} |")
    families = defaultdict(int)
    for r in rows:
        families[r["env"]] += not math.isnan(r["p_value"])
    lines += [
        "",
        "Two-sided permutation test of the difference of the mean final returns (scipy.stats.permutation_test,",
        "independent samples): exact over all C(n + m, n) relabelings of the runs (252 for 5 vs 5, smallest",
        "possible p = 2/252 = 0.0079). Holm's correction across the tested pairs of one task ("
        + ", ".join(f"{env}: {count}" for env, count in sorted(families.items())) + " pairs).",
        f"A difference is called one only when the Holm-corrected p is below {SIGNIFICANCE}.",
    ]
    md_path.write_text("\n".join(lines) + "\n")
    return csv_path, md_path


AGGREGATE_COLUMNS = ("algorithm", "ratio", "tasks", "runs_per_task", "iqm", "iqm_ci_low", "iqm_ci_high", "probability", "probability_ci_low", "probability_ci_high")


def normalisation(runs: list[dict]) -> dict[str, dict]:
    """Per env with a TD3 row and recorded initial returns: ``random``, the mean ``initial_return``
    over every run of the env (the policies as built, before training), and ``td3``, the mean final
    return of the TD3 row. An env where TD3 does not end above ``random`` has no normalisation."""
    groups = table_groups(runs)
    out = {}
    for env in sorted({key[0] for key in groups}):
        td3 = groups.get((env, "td3", ""))
        initial = [run["summary"]["initial_return"] for run in runs if run["summary"]["env"] == env and run["summary"].get("initial_return") is not None]
        if not td3 or not initial:
            continue
        random, reference = float(np.mean(initial)), float(np.mean([s["final_return"] for s in td3]))
        if reference > random:
            out[env] = {"random": random, "td3": reference, "runs": len(initial)}
    return out


def normalised_scores(runs: list[dict]) -> tuple[dict[tuple[str, str], np.ndarray], list[str]]:
    """(row -> normalised final returns, runs x tasks; tasks): score = (final - random) / (td3 -
    random) per task (:func:`normalisation`), 0 = the initial policy, 1 = TD3's mean. A row enters
    when it has runs on every normalised task; its runs are the seeds it has on all of them."""
    norms = normalisation(runs)
    tasks = sorted(norms)
    groups = table_groups(runs)
    scores = {}
    keys = {(a, r) for e, a, r in groups if TD3_ACTOR_SUFFIX not in a}
    for key in sorted(keys, key=row_order):
        by_task = [{s["seed"]: s["final_return"] for s in groups.get((env, *key), [])} for env in tasks]
        seeds = sorted(set.intersection(*(set(d) for d in by_task))) if by_task else []
        if seeds:
            scores[key] = np.array([[(d[seed] - norms[env]["random"]) / (norms[env]["td3"] - norms[env]["random"]) for env, d in zip(tasks, by_task)] for seed in seeds])
    return scores, tasks


def aggregate_table(runs: list[dict], reference: tuple[str, str] = ("es_td3_buffers", PAPER_RATIO)) -> list[dict]:
    """Across tasks (2 or more normalised ones): per row, rliable's aggregate IQM of the normalised
    scores with its 95% stratified-bootstrap CI, and the probability that ``reference`` improves on
    the row (rliable: the mean over tasks of the per-task probability), with its CI."""
    scores, tasks = normalised_scores(runs)
    if len(tasks) < 2:
        return []
    _, metrics = _rliable()
    rows = []
    for key, matrix in scores.items():
        iqm, low, high = _interval({"row": matrix}, lambda x: np.array([metrics.aggregate_iqm(x)]), 0)
        probability, p_low, p_high = (math.nan,) * 3
        if key != reference and reference in scores:
            mine = scores[reference]
            probability = float(metrics.probability_of_improvement(mine, matrix))
            if len(mine) > 1 and len(matrix) > 1:
                _, p_low, p_high = _interval({"x,y": (mine, matrix)}, metrics.probability_of_improvement, 0)
        rows.append({"algorithm": key[0], "ratio": key[1], "tasks": len(tasks), "runs_per_task": len(matrix), "iqm": iqm, "iqm_ci_low": low, "iqm_ci_high": high,
                     "probability": probability, "probability_ci_low": p_low, "probability_ci_high": p_high})
    return rows


def write_aggregate_table(rows: list[dict], runs: list[dict], out_dir: Path) -> tuple[Path, Path]:
    """``aggregate.csv`` and ``aggregate.md``: :func:`aggregate_table` and the normalisation used."""
    csv_path, md_path = out_dir / "aggregate.csv", out_dir / "aggregate.md"
    _write_csv(csv_path, AGGREGATE_COLUMNS, rows)
    norms = normalisation(runs)
    tasks = ", ".join(sorted(norms))
    lines = [f"Across {len(norms)} tasks ({tasks}), normalised final returns:", "",
             "| row | runs per task | aggregate IQM [95% CI] | P(ES-TD3Buffers > row) [95% CI] |", "|---|---:|---|---|"]
    for r in rows:
        probability = "" if math.isnan(r["probability"]) else f"{r['probability']:.2f} {_ci_text(r['probability_ci_low'], r['probability_ci_high'], 2)}"
        lines.append(f"| {label(r['algorithm'], r['ratio'])} | {r['runs_per_task']} | {r['iqm']:.2f} {_ci_text(r['iqm_ci_low'], r['iqm_ci_high'], 2)} | {probability} |")
    lines += ["", "| task | random (mean initial return) | TD3 (mean final return) |", "|---|---:|---:|"]
    lines += [f"| {env} | {n['random']:.1f} | {n['td3']:.1f} |" for env, n in sorted(norms.items())]
    left_out = sorted({run["summary"]["env"] for run in runs} - set(norms))
    if left_out:
        lines += ["", f"Left out (no TD3 row, no recorded initial returns, or TD3 not above the initial policy): {', '.join(left_out)}."]
    lines += [
        "",
        "Normalised score = (final return - random) / (TD3 - random), per task: 0 is the policy as built (the mean of",
        "every run's `initial_return`, the untrained actor evaluated on the final episodes), 1 is the TD3 baseline's mean",
        "final return. There are no published random and expert scores for these tasks at this budget; this scale puts",
        "every task's untrained start and its TD3 at the same two points, so a row's score says how far it got beyond",
        "the start relative to TD3 at the same TD3 frames. Aggregate IQM: interquartile mean over all runs x tasks;",
        "probability of improvement: the mean over tasks of P(a run of ES-TD3Buffers ends above a run of the row);",
        "CIs: rliable's stratified bootstrap (runs resampled within each task).",
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


def _curve_x(run: dict, axis: str = "td3") -> np.ndarray:
    """x of one run's curve: ``"td3"``, its TD3 frames (OpenAI-ES, which has none: the TD3 frames
    ES-TD3Buffers has at the same iteration, ``(iteration + 1) x frames_per_iteration``), or
    ``"total"``, its TD3 + ES frames."""
    if axis == "total":
        return np.array([row["total_frames"] for row in run["metrics"]], dtype=float)
    frames = np.array([row["td3_frames"] for row in run["metrics"]], dtype=float)
    if frames.any():
        return frames
    per_iteration = run["summary"].get("frames_per_iteration", 1)
    return np.array([(row["iteration"] + 1) * per_iteration for row in run["metrics"]], dtype=float)


def _pyplot():
    """matplotlib's pyplot on the file-only Agg backend (reports run headless), with the report's font sizes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update(FONT)
    return plt


FIGURE_DPI = 120
FONT = {"font.size": 9, "axes.titlesize": 9.5, "axes.labelsize": 9, "legend.fontsize": 8, "xtick.labelsize": 8, "ytick.labelsize": 8}
PANEL_WIDTH, PANEL_HEIGHT = 3.3, 2.7  # inches: three panels make a 10-inch row, readable at page width
MAX_COLUMNS, MAX_LINES = 3, 5
BAND = "95% bootstrap CI of the mean over seeds"


def _save(fig, path: Path) -> Path:
    fig.savefig(path, dpi=FIGURE_DPI, bbox_inches="tight")
    _pyplot().close(fig)
    return path


def _grid(panels: int, columns: int = MAX_COLUMNS, width: float = PANEL_WIDTH, height: float = PANEL_HEIGHT, **kwargs):
    """A figure of ``panels`` axes wrapped at ``columns`` per row; axes beyond ``panels`` hidden."""
    plt = _pyplot()
    columns = max(1, min(columns, panels))
    rows = math.ceil(panels / columns)
    fig, axes = plt.subplots(rows, columns, figsize=(width * columns, height * rows), squeeze=False, **kwargs)
    axes = axes.ravel()
    for ax in axes[panels:]:
        ax.set_visible(False)
    return fig, axes


def mean_band(values: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean over seeds (axis 0) and its 95% percentile-bootstrap CI (``scipy.stats.bootstrap``,
    2,000 resamples of the seeds); the band is the mean itself where the seeds agree or there is
    one seed."""
    from scipy import stats

    values = np.asarray(values, dtype=float)
    mean = values.mean(axis=0)
    if len(values) < 2:
        return mean, mean, mean
    with warnings.catch_warnings(), np.errstate(invalid="ignore"):
        warnings.simplefilter("ignore")
        ci = stats.bootstrap((values,), np.mean, axis=0, vectorized=True, method="percentile", n_resamples=BOOTSTRAP_REPS, rng=np.random.default_rng(seed)).confidence_interval
    low, high = np.where(np.isfinite(ci.low), ci.low, mean), np.where(np.isfinite(ci.high), ci.high, mean)
    return mean, np.minimum(low, mean), np.maximum(high, mean)


def _curve_groups(runs: list[dict]) -> dict[str, dict[tuple[str, str], list[dict]]]:
    """env -> (algorithm, ratio) -> runs, ES-TD3Buffers at one ratio only: the paper's when it has
    the most runs or ties (a ratio sweep has its own figure, :func:`plot_ratio_sweep`)."""
    by_env: dict[str, dict[tuple[str, str], list[dict]]] = defaultdict(lambda: defaultdict(list))
    for run in runs:
        if run["metrics"]:
            by_env[run["summary"]["env"]][(run["summary"]["algorithm"], ratio_text(run["summary"]))].append(run)
    out = {}
    for env, by_config in by_env.items():
        ratios = [(len(group), ratio == PAPER_RATIO, ratio) for (algorithm, ratio), group in by_config.items() if ratio]
        main_ratio = max(ratios)[-1] if ratios else ""
        out[env] = {key: group for key, group in by_config.items() if not key[1] or key[1] == main_ratio}
    return out


def curve_panels(keys) -> list[tuple[str, list[tuple[str, str]]]]:
    """The panels of a learning-curve figure, each (title, rows) with at most ``MAX_LINES`` rows:
    the ES-TD3 variants; ES-TD3Buffers against the baselines; the TD3 actors inside the ES-TD3
    variants against the TD3 baseline. A panel with more rows is split."""
    keys = sorted(keys, key=row_order)
    variants = [k for k in keys if k[0].startswith("es_td3")]
    baselines = [k for k in keys if not k[0].startswith("es_td3")]
    reference = [k for k in variants if k[0] == "es_td3_buffers"][:1]
    actors = [(a + TD3_ACTOR_SUFFIX, r) for a, r in variants] + [k for k in baselines if k[0] == "td3"]
    candidates = [("the ES-TD3 variants (returned ES mean)", variants if len(variants) > 1 else []),
                  ("ES-TD3Buffers vs the baselines (returned policy)", reference + baselines if baselines else []),
                  ("TD3 actors: inside ES-TD3 and TD3 alone", actors if len(actors) > 1 and variants else [])]
    panels = []
    for title, rows in candidates:
        for start in range(0, len(rows), MAX_LINES):
            panels.append((title, rows[start:start + MAX_LINES]))
    return panels or [("returned policy", keys[:MAX_LINES])]


def _row_curve(group: list[dict], algorithm: str, axis: str):
    """x (mean over seeds, per iteration) and the return matrix (seeds x iterations) of a row."""
    length = min(len(run["metrics"]) for run in group)
    column = "td3_eval_return" if algorithm.endswith(TD3_ACTOR_SUFFIX) else "eval_return"
    x = np.mean([_curve_x(run, axis)[:length] for run in group], axis=0)
    returns = np.array([[row[column] for row in run["metrics"][:length]] for run in group], dtype=float)
    return x, returns


def _frames_text(value: float, _=None) -> str:
    """Tick label of a frame count: 40k, 2.4M."""
    for scale, suffix in ((1e6, "M"), (1e3, "k")):
        if abs(value) >= scale:
            return f"{value / scale:g}{suffix}"
    return f"{value:g}"


def _frame_axis(ax, log: bool) -> None:
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    if log:
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_minor_formatter(NullFormatter())
    ax.xaxis.set_major_formatter(FuncFormatter(_frames_text))


def plot_learning_curves(runs: list[dict], out_dir: Path) -> list[Path]:
    """``curves_<env>.png``: evaluation return per iteration, one row of panels per group of rows
    (:func:`curve_panels`, at most five lines each), against TD3 frames (left) and against all
    environment frames, TD3 + ES, on a log axis (right); each row's legend under it. Line: mean
    over seeds; band: its 95% bootstrap CI (:func:`mean_band`). A row keeps its colour in every panel."""
    plt = _pyplot()
    paths = []
    for env, by_config in sorted(_curve_groups(runs).items()):
        def drawable(key) -> bool:  # a TD3-actor line needs its runs' td3_eval_return
            base = (key[0].partition(TD3_ACTOR_SUFFIX)[0], key[1])
            return TD3_ACTOR_SUFFIX not in key[0] or all("td3_eval_return" in run["metrics"][0] for run in by_config[base])

        panels = [(title, [k for k in rows if drawable(k)]) for title, rows in curve_panels(by_config)]
        panels = [(title, rows) for title, rows in panels if rows]
        every = sorted({key for _, rows in panels for key in rows}, key=row_order)
        colours = {key: f"C{i % 10}" for i, key in enumerate(every)}
        legend_heights = [0.2 + 0.17 * math.ceil(len(keys) / 2) for _, keys in panels]
        heights = [h for legend in legend_heights for h in (2.7, legend)]
        fig = plt.figure(figsize=(9.2, sum(heights) + 0.5))
        grid = fig.add_gridspec(len(heights), 2, height_ratios=heights)
        for p, (title, keys) in enumerate(panels):
            for column, axis in enumerate(("td3", "total")):
                ax = fig.add_subplot(grid[2 * p, column])
                for key in keys:
                    group = by_config[(key[0].partition(TD3_ACTOR_SUFFIX)[0], key[1])]
                    x, returns = _row_curve(group, key[0], axis)
                    mean, low, high = mean_band(returns)
                    ax.plot(x, mean, marker="o", markersize=2.5, linewidth=1.4, color=colours[key], label=f"{label(*key)} ({_seeds(len(group))})")
                    ax.fill_between(x, low, high, color=colours[key], alpha=0.15, linewidth=0)
                ax.grid(alpha=0.3)
                ax.set_title(title)
                ax.set_ylabel("evaluation return")
                _frame_axis(ax, log=axis == "total")
                ax.set_xlabel("environment frames, TD3 + ES (log)" if axis == "total" else "TD3 frames (OpenAI-ES: at the same iteration)")
            legend = fig.add_subplot(grid[2 * p + 1, :])
            legend.axis("off")
            legend.legend(*ax.get_legend_handles_labels(), loc="upper center", ncol=2, frameon=False)
        fig.suptitle(f"{env}: deterministic evaluation per iteration\nline: mean over seeds; band: {BAND}", fontsize=10)
        fig.tight_layout()
        paths.append(_save(fig, out_dir / f"curves_{env}.png"))
    return paths


def _run_config(run: dict) -> dict:
    """The run's resolved config (``config.yaml`` as recorded, or Hydra's ``.hydra/config.yaml``); {} if none."""
    from omegaconf import OmegaConf

    for path in (run["dir"] / "config.yaml", run["dir"] / ".hydra" / "config.yaml"):
        if path.exists():
            return OmegaConf.to_container(OmegaConf.load(path))
    return {}


BUFFERS = (("good_size", "good"), ("bad_size", "bad"), ("noisy_size", "noisy"))


def plot_buffer_sizes(runs: list[dict], out_dir: Path) -> list[Path]:
    """``buffers_<env>.png``: items in the good, bad and noisy buffers at the end of each iteration,
    one panel per buffer and one line per seed, for each three-buffer configuration (one panel row
    each), with K (``buffer.min_size``): with ``buffer.renormalize=false`` (Algorithm 1) TD3 learns
    once every buffer with a share holds K; the title says which rule the runs used."""
    paths = []
    for env, by_config in sorted(_curve_groups(runs).items()):
        configs = [key for key in sorted(by_config, key=row_order) if key[0] in ES_TD3_BUFFERS and all("good_size" in r["metrics"][0] for r in by_config[key])]
        if not configs:
            continue
        fig, axes = _grid(len(configs) * len(BUFFERS), height=2.6)
        rules = set()
        for c, key in enumerate(configs):
            group = sorted(by_config[key], key=lambda r: r["summary"]["seed"])[:MAX_LINES]
            buffer_cfg = _run_config(group[0]).get("buffer", {})
            min_size = buffer_cfg.get("min_size")
            rules.add(buffer_cfg.get("renormalize"))
            for (column, name), ax in zip(BUFFERS, axes[c * len(BUFFERS):]):
                for run in group:
                    iterations = [row["iteration"] + 1 for row in run["metrics"]]
                    ax.plot(iterations, [row[column] for row in run["metrics"]], marker="o", markersize=2.5, linewidth=1.2, label=f"seed {run['summary']['seed']}")
                if min_size:
                    ax.axhline(min_size, color="black", linestyle="--", linewidth=1, label=f"K = {min_size:,}")
                ax.set_yscale("log")
                ax.set_title(f"{label(*key)}: {name}")
                ax.set_xlabel("end of iteration")
                ax.set_ylabel("items (log)")
                ax.grid(alpha=0.3, which="both")
            axes[c * len(BUFFERS) + len(BUFFERS) - 1].legend(loc="lower right", framealpha=0.85)  # noisy grows alike in every run: its lower right is free
        rule = {frozenset({False}): "TD3 learns once every buffer with a share holds K",
                frozenset({True}): "TD3 learns from the buffers that hold K, ratio renormalised"}.get(frozenset(rules), "K: the readiness size")
        fig.suptitle(f"{env}: buffer sizes per run ({rule})", fontsize=10)
        fig.tight_layout()
        paths.append(_save(fig, out_dir / f"buffers_{env}.png"))
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


def _config_suffix(algorithm: str, ratio: str) -> str:
    soft = "_soft" if algorithm.endswith("_soft") else ""
    return soft + ("" if ratio == PAPER_RATIO else "_ratio_" + ratio.replace(":", "_"))


def plot_es_vs_td3(runs: list[dict], out_dir: Path) -> list[Path]:
    """``es_vs_td3_<env>[_soft][_ratio_a_b_c].png``, one per three-buffer configuration: its TD3
    actor vs its ES mean per iteration, one panel per run in a grid of at most three columns,
    overwrites marked (the paper's learning-curve figure, run by run)."""
    paths = []
    by_config: dict[tuple[str, str, str], list[dict]] = defaultdict(list)
    for run in runs:
        s = run["summary"]
        if s["algorithm"] in ES_TD3_BUFFERS and run["metrics"] and "td3_eval_return" in run["metrics"][0]:
            by_config[(s["env"], s["algorithm"], ratio_text(s))].append(run)
    for (env, algorithm, ratio), group in sorted(by_config.items()):
        group = sorted(group, key=lambda r: r["summary"]["seed"])
        legend_cell = len(group) % MAX_COLUMNS != 0  # a free cell holds the legend
        fig, axes = _grid(len(group) + legend_cell, height=2.5, sharey=True)
        for ax, run in zip(axes, group):
            _draw_es_vs_td3(ax, run)
            ax.set_title(f"seed {run['summary']['seed']}")
        for ax in axes[::MAX_COLUMNS]:
            ax.set_ylabel("evaluation return")
        handles, labels = {}, []
        for ax in axes[:len(group)]:
            for h, lab in zip(*ax.get_legend_handles_labels()):
                if lab not in handles:
                    handles[lab] = h
                    labels.append(lab)
        fig.suptitle(f"{env}: {label(algorithm, ratio)}, TD3 actor vs ES mean per run", fontsize=10)
        fig.tight_layout()
        if legend_cell:
            axes[len(group)].axis("off")
            axes[len(group)].legend([handles[lab] for lab in labels], labels, loc="center")
        else:  # under the grid (the saved image grows to hold it)
            fig.legend([handles[lab] for lab in labels], labels, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=len(labels), frameon=False)
        paths.append(_save(fig, out_dir / f"es_vs_td3_{env}{_config_suffix(algorithm, ratio)}.png"))
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
    (Section 5). Left: the returned ES mean's evaluation return, mean over seeds with its 95%
    bootstrap CI; right: final return per seed, with the number of overwrites each run made next
    to its dot, and the IQM."""
    paths = []
    by_env: dict[str, dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for run in runs:
        s = run["summary"]
        if s["algorithm"] in ES_TD3_BUFFERS and ratio_text(s) == PAPER_RATIO and run["metrics"]:
            by_env[s["env"]][s["algorithm"]].append(run)
    for env, by_mode in sorted(by_env.items()):
        if len(by_mode) < 2:
            continue
        plt = _pyplot()
        fig, (curves, finals) = plt.subplots(1, 2, figsize=(9, 3.4), gridspec_kw={"width_ratios": [2, 1]})
        for i, algorithm in enumerate(ES_TD3_BUFFERS):
            group = by_mode[algorithm]
            x, returns = _row_curve(group, algorithm, "td3")
            mean, low, high = mean_band(returns)
            curves.plot(x, mean, marker="o", markersize=2.5, color=f"C{i}", label=f"{label(algorithm)} ({_seeds(len(group))})")
            curves.fill_between(x, low, high, color=f"C{i}", alpha=0.15, linewidth=0)
            values = [run["summary"]["final_return"] for run in group]
            spread = i + np.linspace(-0.15, 0.15, len(values)) if len(values) > 1 else np.full(1, float(i))  # equal returns stay apart
            finals.scatter(spread, values, color=f"C{i}", s=18)
            for x, value, run in zip(spread, values, group):
                finals.annotate(str(run["summary"].get("overwrites", "")), (x, value), textcoords="offset points", xytext=(4, -3), fontsize=7)
            finals.hlines(interquartile_mean(values), i - 0.2, i + 0.2, color=f"C{i}")
        curves.set_xlabel("TD3 frames")
        curves.set_ylabel("evaluation return (returned ES mean)")
        curves.set_title(f"line: mean over seeds; band: {BAND}", fontsize=8.5)
        curves.grid(alpha=0.3)
        curves.legend(loc="best", framealpha=0.85)
        finals.set_xticks(range(len(ES_TD3_BUFFERS)), ["hard", "soft"])
        finals.set_xlim(-0.6, len(ES_TD3_BUFFERS) - 0.4)
        finals.set_ylabel("final return")
        finals.set_title("seeds; line: IQM; numbers: overwrites", fontsize=8.5)
        finals.grid(alpha=0.3)
        fig.suptitle(f"{env}: hard vs soft overwrite, ES-TD3Buffers {PAPER_RATIO}", fontsize=10)
        fig.tight_layout()
        paths.append(_save(fig, out_dir / f"hard_vs_soft_{env}.png"))
    return paths


def plot_aggregate(rows: list[dict], tasks: list[str], out_dir: Path) -> list[Path]:
    """``aggregate.png`` (2+ tasks): per row, the aggregate IQM of the normalised scores with its
    95% stratified-bootstrap CI (left), and P(ES-TD3Buffers > row) with its CI (right)."""
    if not rows:
        return []
    plt = _pyplot()
    names = [label(r["algorithm"], r["ratio"]) for r in rows]
    y = np.arange(len(rows))[::-1]
    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 0.45 * len(rows) + 1.4), sharey=True)
    for ax, key, title in ((left, "iqm", "aggregate IQM, normalised score"), (right, "probability", f"P(ES-TD3Buffers {PAPER_RATIO} > row)")):
        for yi, r in zip(y, rows):
            if math.isnan(r[key]):
                continue
            low, high = r[f"{key}_ci_low"], r[f"{key}_ci_high"]
            if not math.isnan(low):
                ax.hlines(yi, low, high, color="C0", linewidth=3, alpha=0.5)
            ax.plot(r[key], yi, "o", color="C0")
        ax.set_title(title)
        ax.grid(alpha=0.3, axis="x")
    left.axvline(0, color="grey", linestyle=":", linewidth=1)
    left.axvline(1, color="grey", linestyle="--", linewidth=1)
    left.set_xlabel("0: initial policy, 1: TD3's mean")
    right.axvline(0.5, color="grey", linestyle="--", linewidth=1)
    right.set_xlim(-0.02, 1.02)
    right.set_xlabel("0.5: no difference")
    left.set_yticks(y, names)
    fig.suptitle(f"Across {len(tasks)} tasks ({', '.join(tasks)}); bars: 95% stratified-bootstrap CI (rliable)", fontsize=10)
    fig.tight_layout()
    return [_save(fig, out_dir / "aggregate.png")]


def make_report(paths, out_dir) -> dict:
    """Everything: the tables (csv + md) and the PNGs; returns what was written."""
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
    pairwise = pairwise_table(runs)
    pairwise_csv, pairwise_md = write_pairwise_table(pairwise, out_dir)
    aggregate = aggregate_table(runs)
    written = {}
    if aggregate:
        written["aggregate_csv"], written["aggregate_md"] = write_aggregate_table(aggregate, runs, out_dir)
    figures = (plot_learning_curves(runs, out_dir) + plot_buffer_sizes(runs, out_dir) + plot_es_vs_td3(runs, out_dir) + plot_ratio_sweep(runs, out_dir)
               + plot_hard_vs_soft(runs, out_dir) + plot_aggregate(aggregate, sorted(normalisation(runs)), out_dir))
    return {"runs": len(runs), "rows": rows, "table_csv": csv_path, "table_md": md_path, "improvement": improvement, "improvement_csv": improvement_csv,
            "improvement_md": improvement_md, "pairwise": pairwise, "pairwise_csv": pairwise_csv, "pairwise_md": pairwise_md, "aggregate": aggregate,
            **written, "figures": figures}
