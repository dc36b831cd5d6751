"""What the records can and cannot say about the buffers, and the per-task summary.

- ``overwrites``: per row whose TD3 actor can overwrite its ES mean, how many runs had their ES mean overwritten by the TD3 actor at
  least once. The buffers feed only the TD3 actor (Algorithm 1), which reaches the returned ES mean
  only through an overwrite: in a run with none, the buffer design could not act on the returned
  policy. Beside it, the returned ES mean against its own TD3 actor, paired by run.
- ``summary``: per task, the IQM of every row, the overwrite counts and the differences that the
  Holm-corrected permutation tests call, each marked when it rests on a row whose ES mean was
  never overwritten (then it is a finding about ES alone, not about the buffers).
- ``iterations``: every iteration of each run that is the only run of its row (a single run is
  shown as a run, never as a statistic).
"""
from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

from torchrl_esrl.report.records import Algorithms, ci_text, frames_text, independent_rows, ratio_text, records_overwrites, table_groups, write_csv
from torchrl_esrl.report.statistics import SIGNIFICANCE, paired_comparison
from torchrl_esrl.report.timing import clock_text, held_text, run_time

OVERWRITE_COLUMNS = ("env", "algorithm", "ratio", "runs", "overwritten_runs", "overwrites_by_seed", "never_overwritten_seeds", "same_as_es_seeds",
                     "es_above_td3_actor", "es_equal_td3_actor", "es_below_td3_actor", "paired_probability")


def overwrite_count(summary: dict, metrics: list[dict]) -> int:
    """How many times the TD3 actor replaced (or, soft, moved) the ES mean in the run: the summary's
    count, else the iterations ``metrics.csv`` marks ``overwritten``."""
    if summary.get("overwrites") is not None:
        return int(summary["overwrites"])
    return sum(row.get("overwritten") is True for row in metrics)


def ever_overwritten(summary: dict, metrics: list[dict]) -> bool:
    """Whether the TD3 actor replaced (or, soft, moved) the ES mean at least once in the run."""
    return overwrite_count(summary, metrics) > 0


def overwrite_table(runs: list[dict], algorithms: Algorithms) -> list[dict]:
    """Per env and row whose runs record overwrites (:func:`records_overwrites`): runs whose ES mean
    was ever overwritten; the seeds of the others, and those of them whose final return equals the
    same seed's run of ``algorithms.es_alone`` exactly; the ES mean against its own TD3 actor, run
    by run (:func:`paired_comparison`)."""
    es_final = {(r["summary"]["env"], r["summary"]["seed"]): r["summary"]["final_return"] for r in runs if r["summary"]["algorithm"] == algorithms.es_alone}
    by_row: dict[tuple[str, str, str], list[dict]] = defaultdict(list)
    for run in runs:
        s = run["summary"]
        if records_overwrites(run):
            by_row[(s["env"], s["algorithm"], ratio_text(s))].append(run)
    rows = []
    for (env, algorithm, ratio), group in sorted(by_row.items(), key=lambda item: (item[0][0], algorithms.row_order(item[0][1:]))):
        group = sorted(group, key=lambda r: r["summary"]["seed"])
        never = [r["summary"]["seed"] for r in group if not ever_overwritten(r["summary"], r["metrics"])]
        same = [r["summary"]["seed"] for r in group
                if r["summary"]["seed"] in never and es_final.get((env, r["summary"]["seed"])) == r["summary"]["final_return"]]
        with_actor = [r["summary"] for r in group if "final_td3_actor_return" in r["summary"]]
        paired = paired_comparison([s["final_return"] for s in with_actor], [s["final_td3_actor_return"] for s in with_actor])
        rows.append({"env": env, "algorithm": algorithm, "ratio": ratio, "runs": len(group), "overwritten_runs": len(group) - len(never),
                     "overwrites_by_seed": " ".join(f"{r['summary']['seed']}:{overwrite_count(r['summary'], r['metrics'])}" for r in group),
                     "never_overwritten_seeds": " ".join(map(str, never)), "same_as_es_seeds": " ".join(map(str, same)),
                     "es_above_td3_actor": paired["above"], "es_equal_td3_actor": paired["ties"], "es_below_td3_actor": paired["below"],
                     "paired_probability": paired["probability"], "has_es_row": any(key[0] == env for key in es_final)})
    return rows


def _seed_list(seeds: list[str]) -> str:
    return ("seed " if len(seeds) == 1 else "seeds ") + ", ".join(seeds)


def overwrite_sentence(row: dict, algorithms: Algorithms) -> str:
    """What the row's runs can and cannot tell about the buffers, from :func:`overwrite_table`."""
    name, n, k = algorithms.label(row["algorithm"], row["ratio"]), row["runs"], row["overwritten_runs"]
    never, same = row["never_overwritten_seeds"].split(), row["same_as_es_seeds"].split()
    text = f"{row['env']}, {name}: the ES mean was overwritten in {k} of {n} runs."
    if not never:
        return text + " In every run the buffers could reach the returned policy through the TD3 actor."
    equal = ""
    if row["has_es_row"]:
        equal = f" ({len(same)} of {len(never)} with the same final return as {algorithms.label(algorithms.es_alone)}'s run of the same seed, bit for bit)"
    if k == 0:
        return text + (f" TD3 never replaced it{equal}: no run of this row can tell anything about its buffers, and a difference"
                       " this row shows is one of ES alone.")
    return text + (f" In {_seed_list(never)} TD3 never replaced it{equal}: the buffers could not act on the returned policy there, so"
                   f" only the {k} overwritten run{'s' if k != 1 else ''} can tell anything about them.")


def overwrite_runs_table(runs: list[dict], algorithms: Algorithms) -> list[str]:
    """Per run whose ``metrics.csv`` gives the overwrite rule's averages (Algorithm 1's last step):
    each iteration (from 1) in which the TD3 actor overwrote the ES mean, with the two averages that
    decided it; over the iterations after the last overwrite (the whole run where there was none),
    the largest average of each; the final return of the ES mean and of its own TD3 actor."""
    chosen = [run for run in runs if records_overwrites(run) and run["metrics"] and "td3_average" in run["metrics"][0]]
    if not chosen:
        return []
    lines = ["| env | row | seed | overwritten in iteration: TD3 actor's average / ES mean's | after the last overwrite (the whole run where none), "
             "the largest average: ES mean's / TD3 actor's | final return: ES mean / TD3 actor |", "|---|---|---:|---|---|---|"]
    for run in sorted(chosen, key=lambda r: (r["summary"]["env"], algorithms.row_order((r["summary"]["algorithm"], ratio_text(r["summary"]))), r["summary"]["seed"])):
        s, metrics = run["summary"], run["metrics"]
        overwritten = [i for i, row in enumerate(metrics) if row["overwritten"] is True]
        at = "; ".join(f"{i + 1}: {metrics[i]['td3_average']:,.1f} / {metrics[i]['es_average']:,.1f}" for i in overwritten) or "never"
        after = metrics[overwritten[-1] + 1:] if overwritten else metrics
        largest = (f"{max(row['es_average'] for row in after):,.1f} / {max(row['td3_average'] for row in after):,.1f}" if after
                   else "- (overwritten in the last iteration)")
        actor = s.get("final_td3_actor_return")
        final = f"{s['final_return']:,.1f} / " + (f"{actor:,.1f}" if actor is not None else "-")
        lines.append(f"| {s['env']} | {algorithms.label(s['algorithm'], ratio_text(s))} | {s['seed']} | {at} | {largest} | {final} |")
    return lines


def write_overwrite_table(rows: list[dict], runs: list[dict], out_dir: Path, algorithms: Algorithms) -> tuple[Path, Path]:
    """``overwrites.csv`` and ``overwrites.md``: :func:`overwrite_table` and its sentences; and
    ``overwrite_runs.md``, each run's overwrites (:func:`overwrite_runs_table`), where runs give them."""
    csv_path, md_path = out_dir / "overwrites.csv", out_dir / "overwrites.md"
    write_csv(csv_path, OVERWRITE_COLUMNS, [{key: r[key] for key in OVERWRITE_COLUMNS} for r in rows])
    es_alone = algorithms.label(algorithms.es_alone or "")
    lines = [f"| env | row | runs | ES mean overwritten (runs) | overwrites per run (seed:count) | never overwritten (seeds) | of these, final return = {es_alone}'s (same seed) |"
             " ES mean vs its own TD3 actor, by run: above / equal / below |", "|---|---|---:|---:|---|---|---|---|"]
    for r in rows:
        same = (r["same_as_es_seeds"] or "none") if r["has_es_row"] else f"no {es_alone} row"
        lines.append(f"| {r['env']} | {algorithms.label(r['algorithm'], r['ratio'])} | {r['runs']} | {r['overwritten_runs']} | {r['overwrites_by_seed']} | {r['never_overwritten_seeds'] or '-'} | "
                     f"{same if r['never_overwritten_seeds'] else '-'} | {r['es_above_td3_actor']} / {r['es_equal_td3_actor']} / {r['es_below_td3_actor']} |")
    lines += [""] + [f"- {overwrite_sentence(r, algorithms)}" for r in rows]
    lines += [
        "",
        "The buffers feed only the TD3 actor (Algorithm 1); the returned policy is the ES mean, which the TD3 actor reaches",
        "only by overwriting it. A run whose ES mean was never overwritten returns what ES found without TD3: it stays in",
        "every table (it is what the algorithm returned) but tells nothing about the buffer design. `: its TD3 actor` rows",
        "are where the buffers act in every run. Above / equal / below: the run's final return of its ES mean against that",
        "of its own TD3 actor on the same final episodes (equal: bit for bit, as after an overwrite in the last iteration);",
        "a count over runs, not a test.",
    ]
    md_path.write_text("\n".join(lines) + "\n")
    per_run = overwrite_runs_table(runs, algorithms)
    if per_run:
        intro = ("After each iteration the rule overwrites the ES mean with the TD3 actor when the TD3 actor's evaluation return, "
                 "averaged over the last `overwrite.window` iterations, exceeds the ES mean's (`td3_average`, `es_average` in "
                 "`metrics.csv`; `torchrl_esrl/algorithm/overwrite.py`). Each run:")
        (out_dir / "overwrite_runs.md").write_text("\n".join([intro, "", *per_run]) + "\n")
    return csv_path, md_path


def _difference_text(pair: dict, unaffected: set, algorithms: Algorithms) -> str:
    first, second = (pair["algorithm"], pair["ratio"]), (pair["other_algorithm"], pair["other_ratio"])
    above, below = (first, second) if pair["mean_difference"] > 0 else (second, first)
    text = f"{algorithms.label(*above)} > {algorithms.label(*below)} (Holm p = {pair['p_holm']:.3f})"
    alone = [algorithms.label(*key) for key in (above, below) if (pair["env"], *key) in unaffected]
    if alone:
        text += f" [{' and '.join(alone)} never overwrote its ES mean: a finding about ES alone, not about buffers]"
    return text


def summary_table(runs: list[dict], results: list[dict], pairwise: list[dict], overwrites: list[dict], algorithms: Algorithms) -> list[dict]:
    """Per env: each independent row's IQM and CI (``results``), the overwrite count of each row
    that records overwrites (``overwrites``) and the differences the corrected tests call (``pairwise``)."""
    by_key = {(r["env"], r["algorithm"], r["ratio"]): r for r in results}
    counts = {(r["env"], r["algorithm"], r["ratio"]): r for r in overwrites}
    unaffected = {key for key, r in counts.items() if r["overwritten_runs"] == 0}
    groups = table_groups(runs)
    rows = []
    for env in sorted({key[0] for key in groups}):
        pairs = [p for p in pairwise if p["env"] == env]
        called = [_difference_text(p, unaffected, algorithms) for p in pairs if p["difference"]]
        tested = [p for p in pairs if not math.isnan(p["p_value"])]
        if not called and tested:
            best = min(tested, key=lambda p: p["p_value"])
            called_text = (f"none (smallest: {algorithms.label(best['algorithm'], best['ratio'])} vs {algorithms.label(best['other_algorithm'], best['other_ratio'])}, "
                           f"p = {best['p_value']:.3f}, Holm {best['p_holm']:.3f})")
        else:
            called_text = "; ".join(called) if called else "none tested"
        cells = {}
        for key in independent_rows(groups, env, algorithms):
            r = by_key[(env, *key)]
            cell = f"{r['iqm']:.1f} {ci_text(r['iqm_ci_low'], r['iqm_ci_high'], 1)}" if r["runs"] > 1 else f"{r['mean']:.1f}: one run"
            if (env, *key) in counts:
                cell += f"; overwritten in {counts[(env, *key)]['overwritten_runs']}/{counts[(env, *key)]['runs']}"
            cells[key] = cell
        rows.append({"env": env, "cells": cells, "pairs": len(tested), "differences": called_text, "runs": {key: by_key[(env, *key)]["runs"] for key in cells},
                     "overwrites_counted": any((env, *key) in counts for key in cells)})
    return rows


def write_summary_table(rows: list[dict], out_dir: Path, algorithms: Algorithms) -> Path:
    """``summary.md``: :func:`summary_table`, one line per task."""
    keys = sorted({key for r in rows for key in r["cells"]}, key=algorithms.row_order)
    lines = ["| task | " + " | ".join(algorithms.label(*key) for key in keys) + f" | differences (Holm p < {SIGNIFICANCE}) |", "|---|" + "---|" * (len(keys) + 1)]
    for r in rows:
        lines.append(f"| {r['env']} | " + " | ".join(r["cells"].get(key, "not run") for key in keys) + f" | {r['differences']} |")
    runs = [str(n) for n in sorted({n for r in rows for n in r["runs"].values()})]
    runs_text = ", ".join(runs[:-1]) + " or " + runs[-1] if len(runs) > 1 else runs[0]
    families = ", ".join(f"{r['env']}: {r['pairs']}" for r in rows)
    lines += [
        "",
        f"Final return of the returned policy ({algorithms.returned_text(key[0] for key in keys)}), IQM over {runs_text} runs with its 95% bootstrap CI"
        " (results.md; a row of one run: its final return)" + ("; overwritten in k/n: runs whose ES mean the TD3 actor replaced at least once (overwrites.md)" if any(r["overwrites_counted"] for r in rows) else "") + ". Differences:",
        f"two-sided permutation test of the means with Holm's correction across the task's tested pairs ({families}; pairwise.md).",
        "No difference called means none shown, not that the rows are equal: pairwise.md gives the smallest shift of a row each test would call.",
    ]
    path = out_dir / "summary.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def single_runs(runs: list[dict]) -> list[dict]:
    """The runs that are the only run of their (env, algorithm, ratio) row."""
    groups = defaultdict(list)
    for run in runs:
        groups[(run["summary"]["env"], run["summary"]["algorithm"], ratio_text(run["summary"]))].append(run)
    return [group[0] for key, group in sorted(groups.items()) if len(group) == 1 and group[0]["metrics"]]


def _value(row: dict, key: str, digits: int = 1) -> str:
    value = row.get(key)
    if isinstance(value, bool):
        return "yes" if value else "no"
    return f"{value:.{digits}f}" if isinstance(value, float) and not math.isnan(value) else ("-" if value in (None, "") else str(value))


def write_iterations(runs: list[dict], out_dir: Path, algorithms: Algorithms) -> Path | None:
    """``iterations.md``: every iteration of each run of :func:`single_runs`, as ``metrics.csv`` has it."""
    chosen = single_runs(runs)
    if not chosen:
        return None
    lines = []
    for run in chosen:
        s, rows = run["summary"], run["metrics"]
        with_actor = "td3_eval_return" in rows[0]
        lines += [f"### {s['env']}, {algorithms.label(s['algorithm'], ratio_text(s))}, seed {s['seed']}: one run", ""]
        facts = [f"final return {s['final_return']:.1f} ({s.get('final_episodes', '?')} episodes)"]
        if s.get("final_td3_actor_return") is not None:
            facts.append(f"its TD3 actor {s['final_td3_actor_return']:.1f}")
        if s.get("initial_return") is not None:
            facts.append(f"the initial policy {s['initial_return']:.1f}")
        names = {"overwrites": "overwrites", "td3_updates": "TD3 updates", "td3_frames": "TD3 frames", "es_frames": "ES frames"}
        facts += [f"{name} {s[key]:,}" for key, name in names.items() if isinstance(s.get(key), int)]
        lines += ["; ".join(facts) + ".", ""]
        header = ["iteration", "returned policy"] + (["TD3 actor", "ES mean overwritten"] if with_actor else [])
        header += ["TD3 updates", "ES frames", "training clock (s)", "iteration (s)"]
        has_buffers = with_actor and "good_size" in rows[0]
        header += ["good / bad / noisy"] if has_buffers else []
        lines += ["| " + " | ".join(header) + " |", "|" + "---:|" * len(header)]
        for i, row in enumerate(rows):
            previous = rows[i - 1] if i else {"es_frames": 0, "wall_time_s": 0.0}
            cells = [str(row["iteration"] + 1), _value(row, "eval_return")]
            cells += [_value(row, "td3_eval_return"), _value(row, "overwritten")] if with_actor else []
            cells += [f"{row['td3_updates']:,}" if isinstance(row.get("td3_updates"), int) else "-", frames_text(row["es_frames"] - previous["es_frames"]),
                      f"{row['wall_time_s']:.0f}", f"{row['wall_time_s'] - previous['wall_time_s']:.0f}"]
            cells += [" / ".join(frames_text(row[k]) for k in ("good_size", "bad_size", "noisy_size"))] if has_buffers else []
            lines.append("| " + " | ".join(cells) + " |")
        time = run_time(run)
        if time.holds or time.open_holds:
            lines += ["", f"The run was held {held_text(time)} (`pauses.txt`), on the clock above where the work around a hold was kept; {clock_text(time)} (`timing.md`)."]
        lines.append("")
    lines += ["Per iteration (`metrics.csv`): the returned policy and the TD3 actor evaluated on the iteration's episodes",
              "(the final return is a fresh evaluation); TD3 updates so far; ES frames of the iteration's ES phase; the training",
              "clock (`wall_time_s`, carried across a resume) at the iteration's end; buffer items at its end."]
    path = out_dir / "iterations.md"
    path.write_text("\n".join(lines) + "\n")
    return path
