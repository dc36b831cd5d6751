"""The report's statistics (rliable): IQM, its stratified-bootstrap CI and the probability of
improvement, on small hand-made score arrays whose answers can be worked out by hand."""
import math

import pytest

from torchrl_esrl.report import interquartile_mean, iqm_confidence_interval, probability_of_improvement


def test_iqm_is_the_mean_of_the_middle_half():
    assert interquartile_mean([1, 2, 3, 4, 5, 6, 7, 100]) == pytest.approx(4.5)  # (3 + 4 + 5 + 6) / 4: 1, 2, 7, 100 cut
    assert interquartile_mean([10, 20]) == pytest.approx(15.0)  # two runs: nothing trimmed


def test_iqm_ci_brackets_the_iqm_within_the_data_and_is_nan_for_one_run():
    values = [100.0, 120.0, 90.0, 300.0, 110.0, 95.0]
    low, high = iqm_confidence_interval(values)
    assert min(values) <= low <= interquartile_mean(values) <= high <= max(values)
    assert low < high
    assert all(math.isnan(v) for v in iqm_confidence_interval([5.0]))
    assert all(math.isnan(v) for v in iqm_confidence_interval([5.0, 5.0, 5.0]))  # no spread: no interval


def test_probability_of_improvement_of_a_dominating_set_is_one_with_a_degenerate_ci():
    point, low, high = probability_of_improvement([10.0, 11.0, 12.0], [1.0, 2.0, 3.0, 4.0])
    assert (point, low, high) == (1.0, 1.0, 1.0)
    assert probability_of_improvement([1.0, 2.0, 3.0], [10.0, 11.0, 12.0])[0] == 0.0


def test_probability_of_improvement_counts_ties_half():
    # x vs y=[2, 2, 2]: 1 loses 3 times, 3 and 4 win 3 times each -> 6 / 9
    assert probability_of_improvement([1.0, 3.0, 4.0], [2.0, 2.0, 2.0])[0] == pytest.approx(2 / 3)
    # 1 loses, 2 ties (0.5 each), 3 wins -> 4.5 / 9
    assert probability_of_improvement([1.0, 2.0, 3.0], [2.0, 2.0, 2.0])[0] == pytest.approx(0.5)
    point, low, high = probability_of_improvement([1.0, 3.0, 4.0, 5.0], [2.0, 2.5, 3.5])
    assert 0.0 <= low <= point <= high <= 1.0 and low < high
    assert all(math.isnan(v) for v in probability_of_improvement([1.0], [0.0, 2.0])[1:])  # one run: no CI


# --- permutation test, Holm, normalised aggregate, figures' building blocks ---------------------------------
import itertools  # noqa: E402
import json  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from torchrl_esrl.report import (  # noqa: E402
    MAX_LINES,
    aggregate_table,
    curve_panels,
    find_runs,
    holm,
    make_report,
    mean_band,
    normalised_scores,
    pairwise_table,
    permutation_test,
)

RECORDS = Path(__file__).resolve().parents[1] / "docs" / "results" / "runs" / "multibuffer"


def enumerated_p(x, y) -> float:
    """Reference: the share of all relabelings whose |difference of means| reaches the observed one."""
    pooled, n = np.concatenate([x, y]), len(x)
    observed = abs(np.mean(x) - np.mean(y))
    hits = total = 0
    for chosen in itertools.combinations(range(len(pooled)), n):
        mask = np.zeros(len(pooled), dtype=bool)
        mask[list(chosen)] = True
        hits += abs(pooled[mask].mean() - pooled[~mask].mean()) >= observed - 1e-9
        total += 1
    return hits / total


def test_permutation_test_of_two_separated_five_run_samples_is_two_in_252():
    p, relabelings, exact = permutation_test([10.0, 11.0, 12.0, 13.0, 14.0], [1.0, 2.0, 3.0, 4.0, 5.0])
    assert (relabelings, exact) == (252, True)
    assert p == pytest.approx(2 / 252)
    assert permutation_test([1.0, 2.0, 3.0], [4.0, 5.0, 6.0])[0] == pytest.approx(2 / 20)  # 3 vs 3: C(6, 3) = 20
    assert permutation_test([5.0] * 5, [5.0] * 5)[0] == pytest.approx(1.0)


def test_permutation_test_matches_an_enumeration_of_every_relabeling():
    rng = np.random.default_rng(3)
    for _ in range(3):
        x, y = rng.normal(0, 1, 5), rng.normal(0.8, 1, 5)
        assert permutation_test(x, y)[0] == pytest.approx(enumerated_p(x, y))


def test_holm_on_known_p_values():
    # sorted 0.005, 0.01, 0.03, 0.04 times 4, 3, 2, 1 = 0.02, 0.03, 0.06, 0.04 -> running max 0.02, 0.03, 0.06, 0.06
    assert holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm([0.5, 0.6]) == pytest.approx([1.0, 1.0])  # capped at 1
    assert holm([0.2]) == pytest.approx([0.2])  # one test: unchanged


def run_record(env, algorithm, seed, final, initial=0.0):
    return {"summary": {"env": env, "algorithm": algorithm, "seed": seed, "final_return": final, "initial_return": initial,
                        "ratio": [0.5, 0.2, 0.3] if algorithm == "es_td3_buffers" else None}, "metrics": [], "dir": Path(".")}


def test_pairwise_table_calls_a_difference_only_after_holm():
    runs = [run_record("A", "es_td3_buffers", s, 100.0 + s) for s in range(5)]
    runs += [run_record("A", "td3", s, 10.0 + s) for s in range(5)]  # fully below: p = 2/252
    runs += [run_record("A", "es", s, 10.5 + s) for s in range(5)]  # fully below the first, overlaps td3
    rows = {(r["algorithm"], r["other_algorithm"]): r for r in pairwise_table(runs)}
    assert len(rows) == 3  # C(3, 2) pairs of one task
    separated = rows[("es_td3_buffers", "td3")]
    assert separated["p_value"] == pytest.approx(2 / 252) and separated["p_holm"] == pytest.approx(3 * 2 / 252) and separated["difference"]
    overlapping = rows[("td3", "es")]
    assert overlapping["p_value"] > 0.5 and not overlapping["difference"]


def test_normalised_scores_put_the_initial_policy_at_zero_and_td3_at_one():
    runs = []
    for env, initial, td3, mine in (("A", -100.0, 100.0, 300.0), ("B", 0.0, 50.0, 25.0)):
        runs += [run_record(env, "td3", s, td3 + (s - 2) * 10, initial=initial) for s in range(5)]  # mean td3
        runs += [run_record(env, "es_td3_buffers", s, mine, initial=initial) for s in range(5)]
    scores, tasks = normalised_scores(runs)
    assert tasks == ["A", "B"]
    assert scores[("es_td3_buffers", "0.5:0.2:0.3")] == pytest.approx(np.tile([2.0, 0.5], (5, 1)))  # (300+100)/200, 25/50
    assert scores[("td3", "")].mean(axis=0) == pytest.approx([1.0, 1.0])
    rows = {r["algorithm"]: r for r in aggregate_table(runs)}
    assert rows["es_td3_buffers"]["iqm"] == pytest.approx(1.25)  # the middle half of five 2.0s and five 0.5s
    assert rows["td3"]["iqm_ci_low"] <= rows["td3"]["iqm"] <= rows["td3"]["iqm_ci_high"]
    assert rows["td3"]["probability"] == pytest.approx(0.5)  # task A: always above (1), task B: always below (0)


def test_mean_band_brackets_the_mean_and_collapses_when_the_seeds_agree():
    values = np.array([[0.0, 1.0], [2.0, 1.0], [4.0, 1.0], [6.0, 1.0], [8.0, 1.0]])
    mean, low, high = mean_band(values)
    assert mean == pytest.approx([4.0, 1.0])
    assert 0.0 <= low[0] < 4.0 < high[0] <= 8.0 and low[1] == high[1] == 1.0


def test_curve_panels_hold_at_most_five_lines():
    keys = [("es_td3_buffers", "0.5:0.2:0.3"), ("es_td3_buffers_soft", "0.5:0.2:0.3"), ("es_td3_shared", ""), ("es_td3_shared_soft", ""),
            ("td3", ""), ("cem_rl", ""), ("es", ""), ("other_a", ""), ("other_b", "")]
    panels = curve_panels(keys)
    assert all(1 <= len(rows) <= MAX_LINES for _, rows in panels)
    assert {key for _, rows in panels for key in rows if "/" not in key[0]} == set(keys)  # every row is drawn


def png_size(path) -> tuple[int, int]:
    data = Path(path).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


@pytest.mark.skipif(not RECORDS.exists(), reason="the recorded multibuffer set is not in this checkout")
def test_report_on_recorded_runs_tests_every_pair_and_aggregates_two_tasks(tmp_path):
    dirs = [RECORDS / env / f"{row}_seed{s}" for env in ("halfcheetah", "walker2d") for row in ("es_td3", "es_td3_shared", "td3") for s in range(5)]
    report = make_report(dirs, tmp_path)
    runs = find_runs(dirs)
    pairs = report["pairwise"]
    assert len(pairs) == 2 * 3  # per task, C(3, 2)
    for row in pairs:
        x = [r["summary"]["final_return"] for r in runs if r["summary"]["env"] == row["env"] and r["summary"]["algorithm"] == row["algorithm"]]
        y = [r["summary"]["final_return"] for r in runs if r["summary"]["env"] == row["env"] and r["summary"]["algorithm"] == row["other_algorithm"]]
        assert row["relabelings"] == 252 and row["p_value"] == pytest.approx(enumerated_p(np.array(x), np.array(y)))
        assert row["p_value"] <= row["p_holm"] <= 1.0 and row["difference"] == (row["p_holm"] < 0.05)
    aggregate = {r["algorithm"]: r for r in report["aggregate"]}
    assert set(aggregate) == {"es_td3_buffers", "es_td3_shared", "td3"} and all(r["tasks"] == 2 and r["runs_per_task"] == 5 for r in aggregate.values())
    for row in aggregate.values():
        assert row["iqm_ci_low"] <= row["iqm"] <= row["iqm_ci_high"]
    for name in ("pairwise.md", "aggregate.md", "results.md", "improvement.md", "runs.md"):
        assert (tmp_path / name).stat().st_size > 200, name
    initial = [json.loads((d / "summary.json").read_text())["initial_return"] for d in dirs if "walker2d" in str(d)]
    assert f"| Walker2d-v5 | {np.mean(initial):.1f} |" in (tmp_path / "aggregate.md").read_text()
    names = {p.name for p in report["figures"]}
    for env in ("HalfCheetah-v5", "Walker2d-v5"):
        assert {f"curves_{env}.png", f"buffers_{env}.png", f"es_vs_td3_{env}.png"} <= names
    assert "aggregate.png" in names
    for path in report["figures"]:  # page width: at most about 10 inches at 120 dpi
        width, height = png_size(path)
        assert width <= 1300 and height <= 1600, (path.name, width, height)


def test_a_row_of_one_run_is_not_tested_and_stays_out_of_the_holm_family():
    assert all(math.isnan(v) for v in permutation_test([1.0], [2.0, 3.0])[:1])
    runs = [run_record("A", "td3", s, 10.0 + s) for s in range(5)] + [run_record("A", "es", s, 100.0 + s) for s in range(5)]
    runs += [run_record("A", "cem_rl", 0, 50.0)]
    rows = {(r["algorithm"], r["other_algorithm"]): r for r in pairwise_table(runs)}
    assert math.isnan(rows[("td3", "cem_rl")]["p_value"]) and not rows[("td3", "cem_rl")]["difference"]
    assert rows[("td3", "es")]["p_holm"] == pytest.approx(2 / 252)  # the only tested pair: a family of one


def test_bootstrap_intervals_are_a_function_of_their_data():
    x, y = [2533.0, 179.7, 2925.7, 1501.7, 2681.3], [736.1, 311.2, 1481.7, 1190.6, 2270.7]
    first = (iqm_confidence_interval(x), probability_of_improvement(x, y))
    for draw in range(4):  # whatever the global numpy stream holds
        np.random.seed(draw)
        np.random.random(draw * 7 + 1)
        assert (iqm_confidence_interval(x), probability_of_improvement(x, y)) == first


def test_a_task_where_td3_stays_at_the_initial_policy_is_left_out_of_the_aggregate(tmp_path):
    from torchrl_esrl.report import normalisation, write_aggregate_table

    runs = []
    for env, td3 in (("A", 100.0), ("B", 50.0), ("C", -5.0)):  # C: TD3 below its initial policy (0)
        runs += [run_record(env, "td3", s, td3 + s) for s in range(3)] + [run_record(env, "es_td3_buffers", s, 60.0 + s) for s in range(3)]
    assert sorted(normalisation(runs)) == ["A", "B"]
    rows = aggregate_table(runs)
    assert all(r["tasks"] == 2 for r in rows)
    write_aggregate_table(rows, runs, tmp_path)
    assert "Left out (no TD3 row, no recorded initial returns, or TD3 not above the initial policy): C." in (tmp_path / "aggregate.md").read_text()
