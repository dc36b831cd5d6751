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
