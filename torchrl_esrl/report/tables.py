"""The report's tables over runs: Table 1 of the paper per row (``results``), one row per run
(``runs``), the probability of improvement of the reference row (``improvement``), the
permutation test of every pair of rows (``pairwise``) and the aggregate over tasks (``aggregate``).
The rows' labels and order, and the rows compared against, are the report's
:class:`~torchrl_esrl.report.records.Algorithms`.

- ``results``: per env x algorithm, the final return of the returned policy (``final_return``)
  over seeds: mean, std (ddof=1), median (the paper's Table 1) and the interquartile mean with a
  95% bootstrap CI over seeds (Agarwal et al. 2021; :mod:`torchrl_esrl.report.statistics`).
- ``improvement``: per env, the probability that the reference row (paper ratio) beats each other
  row on a run drawn at random from each, with its 95% bootstrap CI. Its own TD3 actor is not such
  a row (the same runs: :mod:`torchrl_esrl.report.findings` pairs them by run).
- ``pairwise``: per env, every pair of rows: exact permutation test of the difference of mean
  final returns, Holm's correction across the env's pairs; a difference is called one only when
  the corrected p < 0.05.
- ``aggregate`` (2+ envs with a ``normalise_by`` row): rliable's aggregate IQM and probability of
  improvement on scores normalised per env as (final - random) / (that row - random).
"""
from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from torchrl_esrl.report.records import (PAPER_RATIO, TD3_ACTOR_SUFFIX, Algorithms, ci_text, independent_rows, number_text, ratio_text,
                                         table_groups, write_csv)
from torchrl_esrl.report.statistics import (BOOTSTRAP_DRAWS, SIGNIFICANCE, _rliable, aggregate_iqm, aggregate_probability_of_improvement, bootstrap_method, holm, interquartile_mean, iqm_confidence_interval,
                                            permutation_test, probability_of_improvement, smallest_called_shift, stratified_interval)
from torchrl_esrl.report.timing import net_minutes_text, run_time

TABLE_COLUMNS = ("env", "algorithm", "ratio", "runs", "td3_frames", "es_frames", "mean", "std", "median", "iqm", "iqm_ci_low", "iqm_ci_high")


def _methods(sizes) -> str:
    text = "; ".join(f"{n} runs: {bootstrap_method(n)}" for n in sorted(set(sizes)) if n > 1)
    return text or "no row has two runs: no CI"


def mean_count(counts) -> int | float:
    """The mean of counts over runs: whole where it is, else to one decimal (never truncated)."""
    mean = float(np.mean(counts))
    return int(mean) if mean.is_integer() else round(mean, 1)


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
                "td3_frames": mean_count([s.get("td3_frames", 0) for s in summaries]),
                "es_frames": mean_count([s.get("es_frames", 0) for s in summaries]),
                "mean": float(finals.mean()),
                "std": float(finals.std(ddof=1)) if len(finals) > 1 else math.nan,  # one run has no spread
                "median": float(np.median(finals)),
                "iqm": interquartile_mean(finals),
                "iqm_ci_low": low,
                "iqm_ci_high": high,
            }
        )
    return rows


def write_table(rows: list[dict], out_dir: Path, algorithms: Algorithms) -> tuple[Path, Path]:
    """``results.csv`` and ``results.md`` (Table 1 layout: env x algorithm, mean / std / median)."""
    csv_path, md_path = out_dir / "results.csv", out_dir / "results.md"
    write_csv(csv_path, TABLE_COLUMNS, rows)
    lines = [
        "| env | algorithm | runs | TD3 frames | ES frames | mean | std | median | IQM [95% CI] |",
        "|---|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        ci = ci_text(r["iqm_ci_low"], r["iqm_ci_high"], 1)
        lines.append(f"| {r['env']} | {algorithms.label(r['algorithm'], r['ratio'])} | {r['runs']} | {r['td3_frames']} | {r['es_frames']} | {r['mean']:.1f} | {number_text(r['std'], 1)} | {r['median']:.1f} | {r['iqm']:.1f} {ci} |")
    actor_rows = any(r["algorithm"].endswith(TD3_ACTOR_SUFFIX) for r in rows)
    both = sorted({r["algorithm"] for r in rows if r["td3_frames"] and r["es_frames"] and not r["algorithm"].endswith(TD3_ACTOR_SUFFIX)}, key=lambda a: algorithms.row_order((a, "")))
    lines += [
        "",
        f"Final return: deterministic evaluation of the policy each algorithm returns ({algorithms.returned_text(r['algorithm'] for r in rows)}"
        + ("; its TD3 actor on the `: its TD3 actor` rows" if actor_rows else "") + "). TD3 frames (gradient-based learner's environment",
        "steps) and ES frames (evolution's evaluation episodes) are counted separately"
        + (f": {', '.join(algorithms.label(a) for a in both)} spend both, so at equal TD3 frames they have used many more environment frames in total." if both else ".")
        + (f" {frames}." if (frames := algorithms.frames_text(r["algorithm"] for r in rows)) else ""),
        f"IQM CI: 95% percentile bootstrap over the row's runs ({_methods(r['runs'] for r in rows)}).",
    ]
    md_path.write_text("\n".join(lines) + "\n")
    return csv_path, md_path




IMPROVEMENT_COLUMNS = ("env", "algorithm", "ratio", "other_algorithm", "other_ratio", "runs", "other_runs", "probability", "ci_low", "ci_high")


def improvement_table(runs: list[dict], algorithms: Algorithms) -> list[dict]:
    """Per env: probability of improvement of the reference row (``algorithms.reference`` at the
    paper's ratio) over every other row of the results table but the reference's own TD3 actor (the
    same runs: paired, not two samples), with its 95% bootstrap CI. Envs without reference runs give no rows."""
    groups = table_groups(runs)
    rows = []
    for env in sorted({key[0] for key in groups}):
        reference = algorithms.reference_row((a, r) for e, a, r in groups if e == env)
        if reference is None:
            continue
        mine = groups[(env, *reference)]
        x = [s["final_return"] for s in mine]
        for (other_env, algorithm, ratio), summaries in sorted(groups.items()):
            if other_env != env or (algorithm, ratio) in (reference, (reference[0] + TD3_ACTOR_SUFFIX, reference[1])):
                continue
            y = [s["final_return"] for s in summaries]
            probability, low, high = probability_of_improvement(x, y)
            rows.append({"env": env, "algorithm": reference[0], "ratio": reference[1], "other_algorithm": algorithm, "other_ratio": ratio, "runs": len(x), "other_runs": len(y), "probability": probability, "ci_low": low, "ci_high": high})
    return rows


def write_improvement_table(rows: list[dict], out_dir: Path, algorithms: Algorithms, overwrites: bool = False) -> tuple[Path, Path]:
    """``improvement.csv`` and ``improvement.md``: P(reference > row) per env, with CI; ``overwrites``:
    the report counts overwrites (overwrites.md), and the footnote points there."""
    csv_path, md_path = out_dir / "improvement.csv", out_dir / "improvement.md"
    write_csv(csv_path, IMPROVEMENT_COLUMNS, rows)
    mine = algorithms.label(algorithms.reference or "")
    lines = [f"| env | P({mine} > row) | row | runs ({mine} / row) | 95% CI |", "|---|---:|---|---|---|"]
    for r in rows:
        ci = ci_text(r["ci_low"], r["ci_high"], 2)
        lines.append(f"| {r['env']} | {r['probability']:.2f} | {algorithms.label(r['other_algorithm'], r['other_ratio'])} | {r['runs']} / {r['other_runs']} | {ci} |")
    lines += [
        "",
        f"Probability of improvement (Agarwal et al. 2021, rliable): the chance that a run of {mine} {PAPER_RATIO}",
        "ends with a higher final return than a run of the row, ties counting half; 0.5 = no difference.",
        f"CIs: 95% percentile bootstrap over the two rows' runs ({_methods(r['runs'] for r in rows)} of each row, every pair of resamples).",
        "A difference is called one only by the Holm-corrected permutation tests of pairwise.md, not by a CI here."
        + (" The returned ES mean against its own TD3 actor (the same runs) is counted run by run in overwrites.md." if overwrites else ""),
    ]
    md_path.write_text("\n".join(lines) + "\n")
    return csv_path, md_path


PAIRWISE_COLUMNS = ("env", "algorithm", "ratio", "other_algorithm", "other_ratio", "runs", "other_runs", "mean_difference",
                    "relabelings", "exact", "p_value", "p_holm", "difference", "called_shift", "called_difference")


def pairwise_table(runs: list[dict], algorithms: Algorithms) -> list[dict]:
    """Per env, every pair of rows (TD3-actor rows left out: same runs as their row): the
    permutation test of :func:`permutation_test` on the final returns, and Holm's correction
    across that env's tested pairs (a row of one run is not tested: NaN). ``difference`` is True
    only when the corrected p < ``SIGNIFICANCE``. ``called_shift``: :func:`smallest_called_shift`
    of the row against the other row, the family's other p-values as they are; ``called_difference``:
    the difference of means at that shift."""
    groups = table_groups(runs)
    rows = []
    for env in sorted({key[0] for key in groups}):
        keys = independent_rows(groups, env, algorithms)
        env_rows = []
        for i, first in enumerate(keys):
            for second in keys[i + 1:]:
                x = [s["final_return"] for s in groups[(env, *first)]]
                y = [s["final_return"] for s in groups[(env, *second)]]
                p_value, relabelings, exact = permutation_test(x, y)
                env_rows.append({"env": env, "algorithm": first[0], "ratio": first[1], "other_algorithm": second[0], "other_ratio": second[1],
                                 "runs": len(x), "other_runs": len(y), "mean_difference": float(np.mean(x) - np.mean(y)),
                                 "relabelings": relabelings, "exact": exact, "p_value": p_value, "samples": (x, y)})
        tested = [r for r in env_rows if not math.isnan(r["p_value"])]  # Holm's family: the pairs that were tested
        for i, (row, adjusted) in enumerate(zip(tested, holm([r["p_value"] for r in tested]) if tested else [])):
            shift = smallest_called_shift(*row["samples"], [r["p_value"] for j, r in enumerate(tested) if j != i]) if row["exact"] else math.nan
            row.update(p_holm=float(adjusted), difference=bool(adjusted < SIGNIFICANCE), called_shift=shift, called_difference=row["mean_difference"] + shift)
        for row in env_rows:
            del row["samples"]
            for key, value in (("p_holm", math.nan), ("difference", False), ("called_shift", math.nan), ("called_difference", math.nan)):
                row.setdefault(key, value)
        rows += env_rows
    return rows


def write_pairwise_table(rows: list[dict], out_dir: Path, algorithms: Algorithms) -> tuple[Path, Path]:
    """``pairwise.csv`` and ``pairwise.md``: the permutation tests of :func:`pairwise_table`."""
    csv_path, md_path = out_dir / "pairwise.csv", out_dir / "pairwise.md"
    write_csv(csv_path, PAIRWISE_COLUMNS, rows)
    lines = ["| env | row | other row | runs | mean difference | p (permutation) | p (Holm) | difference? | smallest shift of the row called (mean difference then) |",
             "|---|---|---|---|---:|---:|---:|---|---:|"]
    for r in rows:
        if math.isnan(r["p_value"]):
            p_text, holm_text = "not tested (one run)", "-"
        else:
            p_text, holm_text = f"{r['p_value']:.4f}" + ("" if r["exact"] else " (random relabelings)"), f"{r['p_holm']:.4f}"
        lines.append(f"| {r['env']} | {algorithms.label(r['algorithm'], r['ratio'])} | {algorithms.label(r['other_algorithm'], r['other_ratio'])} | {r['runs']} / {r['other_runs']} | "
                     f"{r['mean_difference']:.1f} | {p_text} | {holm_text} | {'**yes**' if r['difference'] else 'no'} | {shift_text(r['called_shift'], r['called_difference'])} |")
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
        "Smallest shift called: the smallest d (in size) such that adding d to every run of the row would make this exact test,",
        "Holm-corrected with the task's other pairs at their p as they are, call the difference; every larger shift in that",
        "direction is called too (statistics.smallest_called_shift). It is what these runs' spread lets the design detect, not an",
        "estimate of anything; 0: called as it is; none: no shift can be called (the smallest possible p, corrected, is not below "
        f"{SIGNIFICANCE}).",
    ]
    md_path.write_text("\n".join(lines) + "\n")
    return csv_path, md_path


def shift_text(shift: float, difference: float) -> str:
    """A cell of :func:`write_pairwise_table`'s last column."""
    if math.isnan(shift):
        return "-"
    if math.isinf(shift):
        return "none"
    return "0 (called)" if shift == 0 else f"{shift:+.1f} ({difference:.1f})"


AGGREGATE_COLUMNS = ("algorithm", "ratio", "tasks", "runs_per_task", "iqm", "iqm_ci_low", "iqm_ci_high", "probability", "probability_ci_low", "probability_ci_high")


def normalisation(runs: list[dict], algorithms: Algorithms) -> dict[str, dict]:
    """Per env with a ``normalise_by`` row (without a ratio) and recorded initial returns:
    ``random``, the mean ``initial_return`` over every run of the env (the policies as built, before
    training), and ``baseline``, the mean final return of that row. An env where it does not end
    above ``random`` has no normalisation."""
    groups = table_groups(runs)
    out = {}
    for env in sorted({key[0] for key in groups}):
        baseline = groups.get((env, algorithms.normalise_by, ""))
        initial = [run["summary"]["initial_return"] for run in runs if run["summary"]["env"] == env and run["summary"].get("initial_return") is not None]
        if not baseline or not initial:
            continue
        random, reference = float(np.mean(initial)), float(np.mean([s["final_return"] for s in baseline]))
        if reference > random:
            out[env] = {"random": random, "baseline": reference, "runs": len(initial)}
    return out


def normalised_scores(runs: list[dict], algorithms: Algorithms) -> tuple[dict[tuple[str, str], np.ndarray], list[str]]:
    """(row -> normalised final returns, runs x tasks; tasks): score = (final - random) / (baseline
    - random) per task (:func:`normalisation`), 0 = the initial policy, 1 = the ``normalise_by``
    row's mean. A row enters when it has runs on every normalised task; its runs are the seeds it
    has on all of them."""
    norms = normalisation(runs, algorithms)
    tasks = sorted(norms)
    groups = table_groups(runs)
    scores = {}
    keys = {(a, r) for e, a, r in groups if TD3_ACTOR_SUFFIX not in a}
    for key in sorted(keys, key=algorithms.row_order):
        by_task = [{s["seed"]: s["final_return"] for s in groups.get((env, *key), [])} for env in tasks]
        seeds = sorted(set.intersection(*(set(d) for d in by_task))) if by_task else []
        if seeds:
            scores[key] = np.array([[(d[seed] - norms[env]["random"]) / (norms[env]["baseline"] - norms[env]["random"]) for env, d in zip(tasks, by_task)] for seed in seeds])
    return scores, tasks


def aggregate_table(runs: list[dict], algorithms: Algorithms) -> list[dict]:
    """Across tasks (2 or more normalised ones): per row, rliable's aggregate IQM of the normalised
    scores with its 95% stratified-bootstrap CI, and the probability that the reference row improves
    on the row (rliable: the mean over tasks of the per-task probability), with its CI."""
    scores, tasks = normalised_scores(runs, algorithms)
    if len(tasks) < 2:
        return []
    _, metrics = _rliable()
    reference = algorithms.reference_row(scores)
    rows = []
    for key, matrix in scores.items():
        iqm = float(metrics.aggregate_iqm(matrix))
        _, low, high = stratified_interval([matrix], aggregate_iqm)
        probability, p_low, p_high = (math.nan,) * 3
        if reference is not None and key != reference:
            mine = scores[reference]
            probability = float(metrics.probability_of_improvement(mine, matrix))
            if len(mine) > 1 and len(matrix) > 1:
                _, p_low, p_high = stratified_interval([mine, matrix], aggregate_probability_of_improvement)
        rows.append({"algorithm": key[0], "ratio": key[1], "tasks": len(tasks), "runs_per_task": len(matrix), "iqm": iqm, "iqm_ci_low": low, "iqm_ci_high": high,
                     "probability": probability, "probability_ci_low": p_low, "probability_ci_high": p_high})
    return rows


def write_aggregate_table(rows: list[dict], runs: list[dict], out_dir: Path, algorithms: Algorithms) -> tuple[Path, Path]:
    """``aggregate.csv`` and ``aggregate.md``: :func:`aggregate_table` and the normalisation used."""
    csv_path, md_path = out_dir / "aggregate.csv", out_dir / "aggregate.md"
    write_csv(csv_path, AGGREGATE_COLUMNS, rows)
    norms = normalisation(runs, algorithms)
    tasks = ", ".join(sorted(norms))
    mine, baseline = algorithms.label(algorithms.reference or ""), algorithms.label(algorithms.normalise_by or "")
    lines = [f"Across {len(norms)} tasks ({tasks}), normalised final returns:", "",
             f"| row | runs per task | aggregate IQM [95% CI] | P({mine} > row) [95% CI] |", "|---|---:|---|---|"]
    for r in rows:
        probability = "" if math.isnan(r["probability"]) else f"{r['probability']:.2f} {ci_text(r['probability_ci_low'], r['probability_ci_high'], 2)}"
        lines.append(f"| {algorithms.label(r['algorithm'], r['ratio'])} | {r['runs_per_task']} | {r['iqm']:.2f} {ci_text(r['iqm_ci_low'], r['iqm_ci_high'], 2)} | {probability} |")
    lines += ["", f"| task | random (mean initial return) | {baseline} (mean final return) |", "|---|---:|---:|"]
    lines += [f"| {env} | {n['random']:.1f} | {n['baseline']:.1f} |" for env, n in sorted(norms.items())]
    left_out = sorted({run["summary"]["env"] for run in runs} - set(norms))
    if left_out:
        lines += ["", f"Left out (no {baseline} row, no recorded initial returns, or {baseline} not above the initial policy): {', '.join(left_out)}."]
    lines += [
        "",
        f"Normalised score = (final return - random) / ({baseline} - random), per task: 0 is the policy as built (the mean of",
        f"every run's `initial_return`, the untrained actor evaluated on the final episodes), 1 is the {baseline} baseline's mean",
        "final return. There are no published random and expert scores for these tasks at this budget; this scale puts",
        f"every task's untrained start and its {baseline} at the same two points, so a row's score says how far it got beyond",
        f"the start relative to {baseline} at the same TD3 frames. Aggregate IQM: interquartile mean over all runs x tasks;",
        f"probability of improvement: the mean over tasks of P(a run of {mine} ends above a run of the row);",
        f"CIs: stratified percentile bootstrap (runs resampled within each task, as rliable's), {BOOTSTRAP_DRAWS:,} random resamples.",
    ]
    md_path.write_text("\n".join(lines) + "\n")
    return csv_path, md_path


RUN_COLUMNS = ("env", "algorithm", "ratio", "seed", "final_return", "final_td3_actor_return", "overwrites", "td3_frames", "es_frames",
               "td3_updates", "first_td3_update", "wall_time_s", "held_s", "wall_time_net_s", "wall_time_net_low_s", "dir")
# The counters of a run that copies its learner into its population (metrics.csv, cumulative): the copies, and
# those that scored among the population's elites in the generation after their copy.
COPY_COLUMNS = ("injections", "injected_elites")


def learner_copies(metrics: list[dict]) -> dict:
    """``COPY_COLUMNS`` at the run's last row (``""`` for a run that logs none)."""
    last = metrics[-1] if metrics else {}
    return {key: int(float(last[key])) if last.get(key) not in (None, "") else "" for key in COPY_COLUMNS}


def first_td3_update(metrics: list[dict]) -> int | str:
    """The iteration (from 1) whose row first counts TD3 updates: when TD3 started learning,
    which with three buffers waits for every buffer to hold K (Algorithm 1). ``"never"`` when no
    row counts one; ``""`` for a run that logs no ``td3_updates``."""
    if not metrics or "td3_updates" not in metrics[0]:
        return ""
    return next((i + 1 for i, row in enumerate(metrics) if row["td3_updates"]), "never")


def write_runs_table(runs: list[dict], out_dir: Path, algorithms: Algorithms) -> tuple[Path, Path]:
    """``runs.csv`` and ``runs.md``: one row per run (seed), the numbers behind each table row; its
    training clock net of the holds placed in it (``wall_time_net_s``; less every hold:
    ``wall_time_net_low_s``) with the held seconds beside (:func:`~torchrl_esrl.report.timing.run_time`)."""
    rows = []
    for run in runs:
        s, time = run["summary"], run_time(run)
        low, high = time.clock_net or ("", "")
        rows.append({**{key: s.get(key, "") for key in RUN_COLUMNS}, "ratio": ratio_text(s), "dir": str(run["dir"]),
                     "first_td3_update": first_td3_update(run["metrics"]), "held_s": time.held, "wall_time_net_s": high, "wall_time_net_low_s": low,
                     "net_minutes": net_minutes_text(time), **learner_copies(run["metrics"])})
    rows.sort(key=lambda r: (r["env"], r["algorithm"], r["ratio"], r["seed"]))
    copies = any(r["injections"] != "" for r in rows)  # the column only where a run copies its learner in
    columns = (*RUN_COLUMNS, *COPY_COLUMNS) if copies else RUN_COLUMNS
    csv_path, md_path = out_dir / "runs.csv", out_dir / "runs.md"
    write_csv(csv_path, columns, [{key: r[key] for key in columns} for r in rows])

    def number(value, digits=1):
        return f"{value:.{digits}f}" if isinstance(value, (int, float)) else "-"

    copy_header = "| learner copied in (as elite) " if copies else ""
    lines = [
        f"| env | algorithm | seed | final return | TD3 actor | overwrites {copy_header}| TD3 frames | ES frames | TD3 updates "
        "| first TD3 update (iteration) | training clock net of holds (min) | held (min) |",
        "|---|---|---:|---:|---:|---:|" + "---:|" * (6 + copies),
    ]
    for r in rows:
        overwrites = r["overwrites"] if r["overwrites"] != "" else "-"
        copied = "" if not copies else f"{r['injections']} ({r['injected_elites']}) | " if r["injections"] != "" else "- | "
        lines.append(
            f"| {r['env']} | {algorithms.label(r['algorithm'], r['ratio'])} | {r['seed']} | {number(r['final_return'])} | "
            f"{number(r['final_td3_actor_return'])} | {overwrites} | {copied}{r['td3_frames']} | {r['es_frames']} | "
            f"{r['td3_updates'] if r['td3_updates'] != '' else '-'} | {r['first_td3_update'] or '-'} | {r['net_minutes']} | {number(r['held_s'] / 60) if r['held_s'] else '-'} |"
        )
    if copies:
        lines += ["", "Learner copied in: how often the run copied its learner over the weakest member of its population; in brackets, the "
                      "copies that scored among the population's elites in the generation that played them (`metrics.csv`'s "
                      "`injections`, `injected_elites`)."]
    held = [r for r in rows if r["held_s"]]
    if held:
        lines += ["", f"Training clock: `summary.json`'s `wall_time_s` less the holds of `pauses.txt` placed in it; a range where a hold fell where the records "
                      f"cannot say whether the clock counted it (timing.md). {len(held)} of {len(rows)} runs were held."]
    md_path.write_text("\n".join(lines) + "\n")
    return csv_path, md_path


