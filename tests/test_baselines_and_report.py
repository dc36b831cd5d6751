"""The baseline recipes (TD3, OpenAI-ES, CEM-RL, single-buffer ES-TD3) and the report, on real
short MuJoCo runs. One module-scoped fixture runs every recipe once; the report reads them."""
import csv
import functools
import json
import math
import statistics
import subprocess
import sys
from pathlib import Path

import pytest

from torchrl_esrl.run.metrics import CORE_COLUMNS, read_metrics

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.e2e


def run_ok(run_recipe, script, *overrides):
    result = run_recipe(script, *overrides)
    assert result.returncode == 0, result.stderr[-3000:]


@pytest.fixture(scope="module")
def runs(tmp_path_factory, run_recipe):
    root = tmp_path_factory.mktemp("runs")
    run = functools.partial(run_ok, run_recipe)
    run("td3.py", "seed=0", "td3.random_frames=300", f"hydra.run.dir={root}/td3_0")
    run("td3.py", "seed=1", f"hydra.run.dir={root}/td3_1")
    run("es.py", "seed=0", f"hydra.run.dir={root}/es_0")
    run("es.py", "seed=1", f"hydra.run.dir={root}/es_1")
    run("cem_rl.py", "seed=0", "cem.population_size=4", "cem.start_frames=0", f"hydra.run.dir={root}/cem_0")
    run("es_td3.py", "seed=0", "buffer.mode=shared", f"hydra.run.dir={root}/shared_0")
    run("es_td3.py", "-m", "seed=0", "buffer.ratio=[0.5,0.2,0.3],[0.2,0.2,0.6]", f"hydra.sweep.dir={root}/sweep")
    run("es_td3.py", "seed=0", "overwrite.mode=soft", "overwrite.mix=0.5", f"hydra.run.dir={root}/soft_0")
    return root


def load(run_dir):
    return read_metrics(run_dir / "metrics.csv"), json.loads((run_dir / "summary.json").read_text())


def check_core(rows, summary, algorithm):
    assert set(CORE_COLUMNS) <= set(rows[0])
    assert [r["iteration"] for r in rows] == [0, 1]
    assert all(math.isfinite(r["eval_return"]) for r in rows)
    assert all(r["total_frames"] == r["td3_frames"] + r["es_frames"] for r in rows)
    assert summary["algorithm"] == algorithm and summary["env"] == "HalfCheetah-v5"
    assert math.isfinite(summary["final_return"]) and summary["td3_frames"] == rows[-1]["td3_frames"]


def test_td3_recipe_one_buffer_no_es(runs):
    rows, summary = load(runs / "td3_0")
    check_core(rows, summary, "td3")
    assert [r["td3_frames"] for r in rows] == [400, 800] and all(r["es_frames"] == 0 for r in rows)
    # learning starts once the buffer holds K=256 (after 300 frames), then one update per frame
    assert [r["td3_updates"] for r in rows] == [150, 550]
    assert summary["seed"] == 0 and load(runs / "td3_1")[1]["seed"] == 1
    assert load(runs / "td3_1")[1]["final_return"] != summary["final_return"]  # seeds differ


def test_es_recipe_no_td3(runs):
    rows, summary = load(runs / "es_0")
    check_core(rows, summary, "es")
    assert all(r["td3_frames"] == 0 for r in rows)
    assert [r["es_frames"] for r in rows] == [800, 1600]  # 4 offspring x 100 steps x 2 generations
    assert [r["es_generations"] for r in rows] == [2, 4]


def test_cem_rl_recipe_trains_half_the_population(runs):
    rows, summary = load(runs / "cem_0")
    check_core(rows, summary, "cem_rl")
    # one generation of 4 x 100 frames per iteration; every frame enters the TD3 buffer
    assert [r["td3_frames"] for r in rows] == [400, 800] and [r["generations"] for r in rows] == [1, 2]
    # generation 1: buffer empty, no TD3; generation 2 (F = 400 frames of generation 1), per RL
    # member (2 of 4): a fresh Adam, F / 2 = 200 critic steps, then F = 400 actor steps
    assert [r["td3_updates"] for r in rows] == [0, 400] and [r["actor_steps"] for r in rows] == [0, 800]


def test_shared_buffer_ablation_puts_everything_in_one_buffer(runs):
    rows, summary = load(runs / "shared_0")
    check_core(rows, summary, "es_td3_shared")
    assert summary["buffer_mode"] == "shared" and summary["ratio"] == [0.0, 0.0, 1.0]
    assert all(r["good_size"] == 0 and r["bad_size"] == 0 for r in rows)
    assert rows[-1]["noisy_size"] == rows[-1]["td3_frames"] + rows[-1]["es_frames"] == 800 + 1600


def test_es_td3_writes_the_core_columns_and_the_returned_policy(runs):
    for run_dir in sorted((runs / "sweep").glob("*/")):
        rows, summary = load(run_dir)
        check_core(rows, summary, "es_td3_buffers")
        for r in rows:  # the returned policy is the ES mean after the overwrite rule
            assert r["eval_return"] == (r["td3_eval_return"] if r["overwritten"] else r["es_eval_return"])
        assert summary["final_es_mean_return"] == summary["final_return"]


def test_soft_overwrite_run_is_its_own_row(runs):
    rows, summary = load(runs / "soft_0")
    check_core(rows, summary, "es_td3_buffers_soft")
    for r in rows:  # not overwritten: the ES mean as evaluated; overwritten: the mixed mean, evaluated anew
        if not r["overwritten"]:
            assert r["eval_return"] == r["es_eval_return"]


def test_report_table_matches_the_runs_and_writes_figures(runs, tmp_path):
    result = subprocess.run([sys.executable, str(ROOT / "recipes" / "report.py"), str(runs), "--out", str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    with (tmp_path / "results.csv").open() as handle:
        table = {(row["algorithm"], row["ratio"]): row for row in csv.DictReader(handle)}
    buffers = [(algorithm, ratio) for algorithm in ("es_td3_buffers", "es_td3_buffers/td3_actor") for ratio in ("0.2:0.2:0.6", "0.5:0.2:0.3")]
    buffers += [("es_td3_buffers_soft", "0.5:0.2:0.3"), ("es_td3_buffers_soft/td3_actor", "0.5:0.2:0.3")]
    others = [(algorithm, "") for algorithm in ("td3", "es", "cem_rl", "es_td3_shared", "es_td3_shared/td3_actor")]
    assert set(table) == set(buffers + others)  # runs at different ratios are never pooled
    finals = [load(runs / d)[1]["final_return"] for d in ("td3_0", "td3_1")]
    td3 = table[("td3", "")]
    assert int(td3["runs"]) == 2 and int(td3["td3_frames"]) == 800
    assert float(td3["mean"]) == pytest.approx(statistics.mean(finals))
    assert float(td3["std"]) == pytest.approx(statistics.stdev(finals))
    assert float(td3["median"]) == pytest.approx(statistics.median(finals))
    assert float(td3["iqm"]) == pytest.approx(statistics.mean(finals))  # 2 values: nothing trimmed
    assert min(finals) - 1e-6 <= float(td3["iqm_ci_low"]) <= float(td3["iqm_ci_high"]) <= max(finals) + 1e-6
    assert all(int(table[key]["runs"]) == 1 for key in buffers) and table[("cem_rl", "")]["iqm_ci_low"] == "nan"  # one seed: no CI
    assert table[("cem_rl", "")]["std"] == "nan" and "| n/a |" in (tmp_path / "results.md").read_text()  # nor a spread
    for run_dir in (runs / "sweep").glob("*/"):
        summary = load(run_dir)[1]
        ratio = ":".join(f"{r:g}" for r in summary["ratio"])
        assert float(table[("es_td3_buffers", ratio)]["mean"]) == pytest.approx(summary["final_return"])
        assert float(table[("es_td3_buffers/td3_actor", ratio)]["mean"]) == pytest.approx(summary["final_td3_actor_return"])
    with (tmp_path / "runs.csv").open() as handle:  # one row per run, the numbers behind the table
        per_run = list(csv.DictReader(handle))
    assert len(per_run) == 9 and sorted(float(r["final_return"]) for r in per_run if r["algorithm"] == "td3") == sorted(finals)
    for r in per_run:  # when TD3 started learning: the first metrics row that counts an update
        rows = load(Path(r["dir"]))[0]
        if "td3_updates" in rows[0]:
            first = next((str(i + 1) for i, row in enumerate(rows) if row["td3_updates"]), "never")
            assert r["first_td3_update"] == first and float(r["td3_updates"]) == rows[-1]["td3_updates"], r["dir"]
    markdown = (tmp_path / "results.md").read_text()
    assert "| HalfCheetah-v5 | TD3 | 2 |" in markdown and "| HalfCheetah-v5 | ES-TD3Buffers 0.5:0.2:0.3: its TD3 actor | 1 |" in markdown
    with (tmp_path / "improvement.csv").open() as handle:  # P(ES-TD3Buffers 0.5:0.2:0.3 > row), every other row
        improvement = {(row["other_algorithm"], row["other_ratio"]): row for row in csv.DictReader(handle)}
    # every other row but its own TD3 actor (the same runs: counted by run in overwrites.md)
    assert set(improvement) == set(table) - {("es_td3_buffers", "0.5:0.2:0.3"), ("es_td3_buffers/td3_actor", "0.5:0.2:0.3")}
    with (tmp_path / "overwrites.csv").open() as handle:  # one row per ES-TD3 row, its runs counted
        overwrites = {(row["algorithm"], row["ratio"]): row for row in csv.DictReader(handle)}
    assert set(overwrites) == {key for key in table if key[0].startswith("es_td3") and "/" not in key[0]}
    for (algorithm, ratio), row in overwrites.items():
        mine = [r for r in per_run if r["algorithm"] == algorithm and r["ratio"] == ratio]
        assert int(row["overwritten_runs"]) == sum(int(r["overwrites"]) > 0 for r in mine)
        assert int(row["es_above_td3_actor"]) == sum(float(r["final_return"]) > float(r["final_td3_actor_return"]) for r in mine)
    assert "| iteration | returned policy | TD3 actor | ES mean overwritten |" in (tmp_path / "iterations.md").read_text()  # the one-run rows
    mine = float(table[("es_td3_buffers", "0.5:0.2:0.3")]["mean"])
    for (algorithm, ratio), row in improvement.items():  # one reference run: P is 0, 0.5 or 1 against each run
        others = [float(r["final_return"]) for r in per_run if r["algorithm"] == algorithm and r["ratio"] == ratio] if "/" not in algorithm else None
        if others is not None:
            assert float(row["probability"]) == pytest.approx(statistics.mean(1.0 if mine > o else 0.5 if mine == o else 0.0 for o in others))
    with (tmp_path / "pairwise.csv").open() as handle:  # every pair of rows with runs of their own, one task: one Holm family
        pairwise = list(csv.DictReader(handle))
    independent = [key for key in table if "/" not in key[0]]
    assert len(pairwise) == len(independent) * (len(independent) - 1) // 2
    for row in pairwise:
        p, p_holm = float(row["p_value"]), float(row["p_holm"])
        if "1" in (row["runs"], row["other_runs"]):  # one run: nothing to relabel against, not tested
            assert math.isnan(p) and math.isnan(p_holm) and row["difference"] == "False"
        else:  # td3 and es have 2 runs each: C(4, 2) = 6 relabelings, the only tested pair, a family of one
            assert {row["algorithm"], row["other_algorithm"]} == {"td3", "es"}
            assert int(row["relabelings"]) == 6 and row["exact"] == "True" and 2 / 6 <= p == p_holm <= 1.0 and row["difference"] == "False"
    assert not (tmp_path / "aggregate.csv").exists()  # one task: nothing to aggregate
    figures = ["curves_HalfCheetah-v5.png", "buffers_HalfCheetah-v5.png", "es_vs_td3_HalfCheetah-v5.png", "es_vs_td3_HalfCheetah-v5_soft.png",
               "es_vs_td3_HalfCheetah-v5_ratio_0.2_0.2_0.6.png", "ratio_sweep_HalfCheetah-v5.png", "hard_vs_soft_HalfCheetah-v5.png"]
    for name in figures:
        png = (tmp_path / name).read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000, name
        assert int.from_bytes(png[16:20], "big") <= 1300, name  # page width: at most about 10 inches at 120 dpi


@pytest.mark.parametrize("name", ["td3_0", "es_0", "cem_0", "shared_0", "sweep/0"])
def test_every_recipe_writes_its_learning_curve_and_initial_return(runs, name):
    _, summary = load(runs / name)
    png = (runs / name / "learning_curve.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert math.isfinite(summary["initial_return"])  # the initial actor, evaluated as the final one is


def test_tensorboard_backend_writes_event_files(run_recipe, tmp_path):
    pytest.importorskip("tensorboard")
    run_ok(run_recipe, "es.py", "iterations=1", "es.generations_per_iteration=1", "logger.backend=tensorboard", f"hydra.run.dir={tmp_path}")
    assert list((tmp_path / "logs").rglob("events.out.tfevents.*"))
    assert (tmp_path / "metrics.csv").exists()
