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
    Algorithms,
    aggregate_table,
    curve_panels,
    find_runs,
    holm,
    make_report,
    mean_band,
    normalised_scores,
    pairwise_table,
    permutation_test,
    smallest_called_shift,
)
from torchrl_esrl.run.algorithm_info import AlgorithmInfo, discover, load_recipe  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "docs" / "results" / "runs" / "multibuffer"
# The recipes' labels and ranks, and the rows recipes/report.py compares against by default.
ALGORITHMS = Algorithms(discover(ROOT / "recipes"), reference="es_td3_buffers", normalise_by="td3", es_alone="es")


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


def test_smallest_called_shift_of_four_against_four_is_the_gap_to_full_separation():
    """4 vs 4, one test: C(8, 4) = 70 relabelings, so only p = 2/70 is below 0.05, and that needs
    every run of one row above every run of the other: x + d above max(y) (d > 7 - 1 = 6) or below
    min(y) (d < 0 - 4 = -4). The smaller shift is -4."""
    x, y = [1.0, 2.0, 3.0, 4.0], [0.0, 5.0, 6.0, 7.0]
    assert smallest_called_shift(x, y) == pytest.approx(-4.0)
    assert smallest_called_shift([10.0, 11.0, 12.0, 13.0], y) == 0.0  # separated already: called as it is
    assert math.isinf(smallest_called_shift([1.0, 2.0, 3.0], [4.0, 5.0, 6.0]))  # 3 vs 3: p >= 2/20, never called
    assert math.isnan(smallest_called_shift([1.0], y))  # one run: no test


def test_smallest_called_shift_follows_holms_step_down():
    """5 vs 5, 6 pairs: alone among p = 0.5, the pair needs p = 2/252 (x + d below min(y): d < 3 - 5 = -2);
    after three pairs at 2/252, Holm calls 4/252 at 3 x 4/252 = 0.048, so one other relabeling may tie or
    pass it: the second-smallest single swap, min(4 - 5, 3 - 4) = -1. With 15 pairs no p can be called."""
    x, y = [1.0, 2.0, 3.0, 4.0, 5.0], [3.0, 4.0, 5.0, 6.0, 7.0]
    assert smallest_called_shift(x, y, [0.5] * 5) == pytest.approx(-2.0)
    assert smallest_called_shift(x, y, [2 / 252] * 3 + [1.0, 1.0]) == pytest.approx(-1.0)
    assert math.isinf(smallest_called_shift(x, y, [0.5] * 14))


@pytest.mark.parametrize("seed", range(4))
def test_smallest_called_shift_is_where_the_corrected_permutation_test_starts_calling(seed):
    rng = np.random.default_rng(seed)
    x, y = rng.normal(0, 1, 5), rng.normal(0.5, 1.5, 5)
    others = [0.01, 0.3] if seed % 2 else [2 / 252, 2 / 252, 2 / 252, 0.9]
    shift = smallest_called_shift(x, y, others)
    assert 0 < abs(shift) < 20

    def called(d):
        return holm([permutation_test(x + d, y)[0], *others])[0] < 0.05

    step = 1e-6 * (1 + abs(shift))
    assert called(shift + math.copysign(step, shift)) and not called(shift - math.copysign(step, shift))
    assert not called(-shift + math.copysign(step, shift))  # the other direction needs at least as large a shift


def run_record(env, algorithm, seed, final, initial=0.0):
    return {"summary": {"env": env, "algorithm": algorithm, "seed": seed, "final_return": final, "initial_return": initial,
                        "ratio": [0.5, 0.2, 0.3] if algorithm == "es_td3_buffers" else None}, "metrics": [], "dir": Path(".")}


def test_pairwise_table_calls_a_difference_only_after_holm():
    runs = [run_record("A", "es_td3_buffers", s, 100.0 + s) for s in range(5)]
    runs += [run_record("A", "td3", s, 10.0 + s) for s in range(5)]  # fully below: p = 2/252
    runs += [run_record("A", "es", s, 10.5 + s) for s in range(5)]  # fully below the first, overlaps td3
    rows = {(r["algorithm"], r["other_algorithm"]): r for r in pairwise_table(runs, ALGORITHMS)}
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
    scores, tasks = normalised_scores(runs, ALGORITHMS)
    assert tasks == ["A", "B"]
    assert scores[("es_td3_buffers", "0.5:0.2:0.3")] == pytest.approx(np.tile([2.0, 0.5], (5, 1)))  # (300+100)/200, 25/50
    assert scores[("td3", "")].mean(axis=0) == pytest.approx([1.0, 1.0])
    rows = {r["algorithm"]: r for r in aggregate_table(runs, ALGORITHMS)}
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
    panels = curve_panels(keys, {key for key in keys if key[0].startswith("es_td3")}, ALGORITHMS)
    assert all(1 <= len(rows) <= MAX_LINES for _, rows in panels)
    assert {key for _, rows in panels for key in rows if "/" not in key[0]} == set(keys)  # every row is drawn


def png_size(path) -> tuple[int, int]:
    data = Path(path).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


@pytest.mark.skipif(not RECORDS.exists(), reason="the recorded multibuffer set is not in this checkout")
def test_report_on_recorded_runs_tests_every_pair_and_aggregates_two_tasks(tmp_path):
    dirs = [RECORDS / env / f"{row}_seed{s}" for env in ("halfcheetah", "walker2d") for row in ("es_td3", "es_td3_shared", "td3") for s in range(5)]
    report = make_report(dirs, tmp_path, ALGORITHMS)
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
    rows = {(r["algorithm"], r["other_algorithm"]): r for r in pairwise_table(runs, ALGORITHMS)}
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
    assert sorted(normalisation(runs, ALGORITHMS)) == ["A", "B"]
    rows = aggregate_table(runs, ALGORITHMS)
    assert all(r["tasks"] == 2 for r in rows)
    write_aggregate_table(rows, runs, tmp_path, ALGORITHMS)
    assert "Left out (no TD3 row, no recorded initial returns, or TD3 not above the initial policy): C." in (tmp_path / "aggregate.md").read_text()


# --- exact bootstrap, paired count, what the overwrites let a run say, the overview --------------------------
from torchrl_esrl.report import overview_rows, overwrite_table, read_paper_table, summary_table, write_iterations, write_overview  # noqa: E402
from torchrl_esrl.report.statistics import (aggregate_iqm, aggregate_probability_of_improvement, paired_comparison,  # noqa: E402
                                            stratified_interval, weighted_quantiles)

MINIATURE = ROOT / "docs" / "results" / "runs" / "miniature"
PAPER_RUNS = ROOT / "docs" / "results" / "runs" / "paper"
PAPER_TABLE = ROOT / "docs" / "results" / "paper_table1.csv"  # the paper's Table 1 as printed


def brute_force_quantiles(statistics_of_every_resample) -> list[float]:
    return list(np.quantile(np.asarray(statistics_of_every_resample), [0.025, 0.975], method="inverted_cdf"))


def test_exact_iqm_ci_is_the_quantiles_over_every_resample():
    from scipy import stats

    values = np.array([3.0, -1.0, 10.0, 4.5])
    every = [stats.trim_mean(values[list(chosen)], 0.25) for chosen in itertools.product(range(4), repeat=4)]  # 4^4 = 256
    assert list(iqm_confidence_interval(values)) == pytest.approx(brute_force_quantiles(every))


def test_exact_iqm_ci_of_five_recorded_runs_differs_from_two_thousand_draws():
    # HalfCheetah-v5 OpenAI-ES, miniature seeds 0-4: 2,000 random draws gave an upper end of 2290.3
    values = [900.902617, -0.398782951, 2539.86408, 0.110290363, 2165.53260]
    low, high = iqm_confidence_interval(values)
    assert low == pytest.approx(-0.229, abs=1e-3) and high == pytest.approx(2415.087, abs=1e-2)


def test_weighted_quantiles_equal_the_quantiles_of_the_repeated_values():
    rng = np.random.default_rng(5)
    for _ in range(20):
        values, weights = rng.integers(0, 6, 30).astype(float), rng.integers(1, 9, 30)  # ties on purpose
        expected = np.quantile(np.repeat(values, weights), [0.025, 0.975], method="inverted_cdf")
        assert list(weighted_quantiles(values, weights)) == list(expected)


def test_exact_probability_of_improvement_ci_enumerates_every_pair_of_resamples():
    x, y = np.array([1.0, 3.0, 4.0]), np.array([2.0, 2.0, 3.0, 5.0])
    every = []
    for a in itertools.product(range(3), repeat=3):  # 27 x 256 pairs
        for b in itertools.product(range(4), repeat=4):
            xa, yb = x[list(a)], y[list(b)]
            every.append(np.mean((xa[:, None] > yb[None, :]) + 0.5 * (xa[:, None] == yb[None, :])))
    point, low, high = probability_of_improvement(x, y)
    assert point == pytest.approx(np.mean((x[:, None] > y[None, :]) + 0.5 * (x[:, None] == y[None, :])))
    assert [low, high] == pytest.approx(brute_force_quantiles(every))
    assert low < point < high


def test_vectorised_aggregate_statistics_equal_rliable_on_each_resample():
    from rliable import metrics

    rng = np.random.default_rng(2)
    x, y = rng.normal(size=(7, 5, 3)), rng.normal(size=(7, 4, 3))
    x[:, 0] = y[:, 0, :]  # ties
    assert aggregate_iqm(x) == pytest.approx([metrics.aggregate_iqm(m) for m in x])
    assert aggregate_probability_of_improvement(x[:, :4], y) == pytest.approx([metrics.probability_of_improvement(a, b) for a, b in zip(x[:, :4], y)])
    point, low, high = stratified_interval([x[0]], aggregate_iqm)
    assert low < point < high and (point, low, high) == stratified_interval([x[0]], aggregate_iqm)  # a function of its data


def test_paired_comparison_counts_runs_not_pairs_of_runs():
    es, actor = [10.0, 5.0, 7.0, 7.0, 1.0], [9.0, 5.0, 8.0, 7.0, 0.0]
    assert paired_comparison(es, actor) == {"runs": 5, "above": 2, "ties": 2, "below": 1, "probability": pytest.approx(0.6)}
    # unpaired, the same numbers give another answer: every run of x against every run of y
    assert probability_of_improvement(es, actor)[0] != pytest.approx(0.6)
    with pytest.raises(ValueError):
        paired_comparison([1.0, 2.0], [1.0])


def es_td3_record(env, algorithm, seed, final, actor, overwrites):
    record = run_record(env, algorithm, seed, final)
    record["summary"].update(final_td3_actor_return=actor, overwrites=overwrites)
    return record


def test_overwrite_table_finds_runs_the_buffers_could_not_reach_and_the_summary_marks_their_differences():
    runs = [run_record("A", "es", s, 100.0 + s) for s in range(5)] + [run_record("A", "td3", s, 10.0 + s) for s in range(5)]
    runs += [es_td3_record("A", "es_td3_shared", s, 100.0 + s if s < 4 else 120.0, 50.0, 0) for s in range(5)]  # never overwritten
    runs += [es_td3_record("A", "es_td3_buffers", s, 200.0 + s, 200.0 + s if s else 150.0, 0 if s == 2 else 3) for s in range(5)]
    rows = {r["algorithm"]: r for r in overwrite_table(runs, ALGORITHMS)}
    shared, buffers = rows["es_td3_shared"], rows["es_td3_buffers"]
    assert (shared["overwritten_runs"], shared["never_overwritten_seeds"], shared["same_as_es_seeds"]) == (0, "0 1 2 3 4", "0 1 2 3")
    assert (buffers["overwritten_runs"], buffers["never_overwritten_seeds"], buffers["same_as_es_seeds"]) == (4, "2", "")
    assert (buffers["es_above_td3_actor"], buffers["es_equal_td3_actor"], buffers["es_below_td3_actor"]) == (1, 4, 0)
    from torchrl_esrl.report import results_table

    (summary,) = summary_table(runs, results_table(runs), pairwise_table(runs, ALGORITHMS), overwrite_table(runs, ALGORITHMS), ALGORITHMS)
    differences = summary["differences"].split("; ")
    assert any(d.startswith("ES-TD3 (one shared buffer) > TD3") and "never overwrote its ES mean" in d for d in differences)
    assert any(d.startswith("ES-TD3Buffers 0.5:0.2:0.3 > TD3") and "never" not in d for d in differences)


def test_returned_policies_are_named_from_the_recipes_grouped_by_policy_in_row_order():
    assert ALGORITHMS.returned_text(["cem_rl", "td3", "es", "es_td3_buffers/td3_actor", "es_td3_buffers"]) == (
        "ES mean: ES-TD3Buffers, OpenAI-ES; TD3 actor: TD3; CEM mean: CEM-RL")
    assert ALGORITHMS.returned_text(["unknown"]) == "returned policy: unknown"


def test_what_td3_frames_count_is_said_only_for_recipes_that_say_it():
    assert ALGORITHMS.frames_text(["td3", "es_td3_buffers"]) == ""
    assert ALGORITHMS.frames_text(["cem_rl_buffers", "td3", "cem_rl"]).startswith("CEM-RL, CEM-RL (return-routed buffers): TD3 frames are every population member's episode")


CEM_RL_BUFFERS = ROOT / "docs" / "results" / "runs" / "cem_rl_buffers"


@pytest.mark.skipif(not any(CEM_RL_BUFFERS.rglob("summary.json")), reason="no recorded CEM-RL run in this checkout")
def test_a_report_of_cem_rl_rows_speaks_of_what_they_return_and_spend(tmp_path):
    """Footnotes come from the rows' recipes: CEM-RL rows return the CEM mean, count their population's
    episodes as TD3 frames, spend no ES frames and overwrite nothing, so neither the ES-TD3 wording
    nor the overwrite count appears."""
    from torchrl_esrl.report import make_report

    algorithms = Algorithms(discover(ROOT / "recipes"), reference="cem_rl_buffers", normalise_by="cem_rl")
    written = make_report([CEM_RL_BUFFERS], tmp_path, algorithms)
    summary, results = written["summary_md"].read_text(), written["table_md"].read_text()
    assert "(CEM mean: CEM-RL, CEM-RL (return-routed buffers))" in summary and "overwritten" not in summary and "ES mean" not in summary
    assert "returns (CEM mean: CEM-RL, CEM-RL (return-routed buffers))." in results and "spend both" not in results
    assert "CEM-RL, CEM-RL (return-routed buffers): TD3 frames are every population member's episode" in results
    assert "overwrites.md" not in written["improvement_md"].read_text()


def test_overview_cells_without_a_record_hold_no_number(tmp_path):
    runs = [run_record("Walker2d-v5", "es_td3_buffers", 0, 6639.1)]
    runs[0]["summary"].update(experiment="paper", td3_frames=2_000_000, es_frames=109_803_211)
    runs += [run_record("Walker2d-v5", "td3", s, 400.0 + s) for s in range(5)]
    for r in runs[1:]:
        r["summary"].update(experiment="miniature", td3_frames=80_000, es_frames=0)
    rows, experiments = overview_rows(runs, ALGORITHMS, read_paper_table(PAPER_TABLE), {("Walker2d-v5", "td3", "paper")})
    assert experiments == ["paper", "miniature"]
    cells = {(r["env"], r["algorithm"], r["experiment"]): r for r in rows}
    assert cells[("Walker2d-v5", "td3", "paper")]["status"] == "running" and "mean" not in cells[("Walker2d-v5", "td3", "paper")]
    assert cells[("Walker2d-v5", "es_td3_buffers", "miniature")]["status"] == "not run"
    assert cells[("Walker2d-v5", "td3", "miniature")]["runs"] == 5
    _, md = write_overview(runs, tmp_path, ALGORITHMS, read_paper_table(PAPER_TABLE), {("Walker2d-v5", "td3", "paper")})
    text = md.read_text()
    assert "| Walker2d-v5 (Walker) | ES-TD3Buffers 0.5:0.2:0.3 | 2217 (std 1454, median 1764) | 6639.1: one run (seed 0), 2M TD3 + 109.8M ES frames | not run |" in text
    assert "| Walker2d-v5 (Walker) | TD3 | 3808 (std 339, median 3882) | running | IQM 402.0" in text


PAPER_TEX = Path(__file__).resolve().parents[2] / "shared" / "paper" / "es_td3buffers.tex"


@pytest.mark.skipif(not PAPER_TEX.exists(), reason="the paper's source is not beside this checkout")
def test_paper_table_1_is_the_papers():
    import re

    paper = read_paper_table(PAPER_TABLE)
    tex = PAPER_TEX.read_text()
    table = tex[tex.index(r"\label{tab:baselines}"):tex.index(r"\end{tabular}")]
    columns = ("td3", "cem", "erl", "cem_rl", "es_td3_buffers")
    numbers = [[int(v) for v in re.findall(r"\d+", line.split("&", 2)[2])] for line in table.splitlines() if re.search(r"(Mean|Std\.|Median) *&", line)]
    assert len(numbers) == 12
    for block, paper_name in enumerate(("HalfCheetah", "Ant", "Swimmer", "Walker")):
        env = next(e for e, task in paper["tasks"].items() if task == paper_name)
        mean, std, median = numbers[3 * block:3 * block + 3]
        assert {c: (mean[i], std[i], median[i]) for i, c in enumerate(columns)} == paper["scores"][env]


@pytest.mark.skipif(not (PAPER_RUNS / "walker2d" / "es_td3_seed0").exists(), reason="the paper-budget record is not in this checkout")
def test_iterations_table_of_the_paper_run_has_every_iteration_under_its_number(tmp_path):
    runs = find_runs([PAPER_RUNS / "walker2d" / "es_td3_seed0"])
    text = write_iterations(runs, tmp_path, ALGORITHMS).read_text()
    rows = [line for line in text.splitlines() if line.startswith("| ") and line[2].isdigit()]
    assert [int(r.split("|")[1]) for r in rows] == list(range(1, 21))
    assert rows[13].startswith("| 14 | 6236.6 | 5521.3 |") and rows[15].startswith("| 16 | 6465.8 | 6019.6 |")


@pytest.mark.skipif(not MINIATURE.exists(), reason="the recorded miniature set is not in this checkout")
def test_miniature_overwrites_and_paired_counts_match_the_records():
    runs = find_runs([MINIATURE])
    rows = {(r["env"], r["algorithm"]): r for r in overwrite_table(runs, ALGORITHMS)}
    assert rows[("Ant-v5", "es_td3_shared")]["overwritten_runs"] == 0 and rows[("Ant-v5", "es_td3_shared")]["same_as_es_seeds"] == "0 1 2 4"
    assert rows[("Ant-v5", "es_td3_buffers")]["never_overwritten_seeds"] == "4"
    assert all(rows[("Swimmer-v5", a)]["never_overwritten_seeds"] == "3" for a in ("es_td3_buffers", "es_td3_shared"))
    paired = {env: tuple(rows[(env, "es_td3_buffers")][k] for k in ("es_above_td3_actor", "es_equal_td3_actor", "es_below_td3_actor"))
              for env in ("Ant-v5", "HalfCheetah-v5", "Swimmer-v5", "Walker2d-v5")}
    assert paired == {"Ant-v5": (4, 0, 1), "HalfCheetah-v5": (2, 3, 0), "Swimmer-v5": (5, 0, 0), "Walker2d-v5": (5, 0, 0)}


RESULTS_PAGE = Path(__file__).resolve().parents[1] / "docs" / "results.md"


@pytest.mark.skipif(not RESULTS_PAGE.exists(), reason="no results page in this checkout")
def test_the_results_page_copies_its_generated_tables_unchanged():
    import re

    blocks = re.findall(r"<!-- ((?:\w+/)*[\w.]+\.md) -->\n(.*?)\n<!-- /\1 -->", RESULTS_PAGE.read_text(), flags=re.S)
    assert len(blocks) >= 7 and {"results.md", "runs.md"} <= {path for path, _ in blocks}
    for path, body in blocks:
        assert body == (RESULTS_PAGE.parent / "results" / path).read_text().rstrip(), path


COMMITTED = load_recipe(ROOT / "scripts" / "committed_reports.py")  # every committed report and its command


@pytest.mark.parametrize("folder", sorted(COMMITTED.REPORTS))
def test_committed_report_tables_are_what_their_command_writes_from_their_records(folder, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(ROOT)  # the commands name their records from the project's root
    load_recipe(ROOT / "recipes" / "report.py").main(COMMITTED.report_arguments(folder, tmp_path))
    written = sorted(tmp_path.glob("*.md"))
    assert written
    for path in written:
        assert (RESULTS_PAGE.parent / "results" / folder / path.name).read_text() == path.read_text(), path.name


def test_the_page_sync_replaces_a_stale_copy_and_nothing_else(tmp_path):
    (tmp_path / "results" / "sub").mkdir(parents=True)
    (tmp_path / "results" / "sub" / "table.md").write_text("| a |\n|---|\n| 2 |\n")
    page = tmp_path / "page.md"
    page.write_text("# Page\n\n<!-- sub/table.md -->\n| a |\n|---|\n| 1 |\n<!-- /sub/table.md -->\n\nmore text\n")
    assert COMMITTED.sync_page(page, tmp_path / "results") == ["sub/table.md"]
    assert page.read_text() == "# Page\n\n<!-- sub/table.md -->\n| a |\n|---|\n| 2 |\n<!-- /sub/table.md -->\n\nmore text\n"


def test_committed_reports_refuse_an_unknown_folder_in_one_line(capsys):
    with pytest.raises(SystemExit) as exit_:
        COMMITTED.main(["nowhere"])
    assert exit_.value.code == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "nowhere" in error and "cem_rl_buffers" in error


def test_committed_reports_name_the_reports_that_read_a_record(tmp_path, capsys):
    """A new record's reports: the overview and its set's report, the paper runs' each their own."""
    assert COMMITTED.reading("docs/results/runs/quarter/walker2d/td3_seed3") == ["overview", "quarter"]
    assert COMMITTED.reading("docs/results/runs/paper/walker2d/td3_seed0") == ["overview", "paper/walker2d_td3"]
    assert COMMITTED.reading(ROOT / "docs/results/runs/table1") == ["overview", "table1"]
    assert COMMITTED.reading(tmp_path / "runs" / "walker2d" / "td3_seed0") == []
    COMMITTED.main(["--reading", str(tmp_path)])  # nothing to write: says so, writes nothing
    assert capsys.readouterr().err == f"{tmp_path}: no committed report reads it\n"
