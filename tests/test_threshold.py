import math

import pytest
import torch

from torchrl_esrl.data.threshold import Threshold


def test_positive_best_gives_ninety_percent():
    threshold = Threshold(0.9)
    threshold.observe(1000.0)
    assert threshold.value == pytest.approx(900.0)
    assert threshold.is_good(950.0)
    assert not threshold.is_good(899.0)


def test_negative_best_stays_below_the_best():
    threshold = Threshold(0.9)
    threshold.observe(-100.0)
    # 0.9 x (-100) = -90 would lie above the best; the sign-safe threshold is -110
    assert threshold.value == pytest.approx(-110.0)
    assert threshold.value < threshold.best
    assert threshold.is_good(-105.0)
    assert not threshold.is_good(-111.0)


@pytest.mark.parametrize("returns", [[-300.0, -250.0, -400.0], [5.0, 1.0, 7.5], [-2.0, 3.0, -1.0], [0.0, 0.0]])
def test_the_best_episode_always_counts_as_good(returns):
    threshold = Threshold(0.9)
    good = threshold.route(returns)
    best = max(range(len(returns)), key=returns.__getitem__)
    assert good[best]
    assert threshold.best == max(returns)


def test_first_return_is_good_and_threshold_starts_at_minus_infinity():
    threshold = Threshold(0.9)
    assert threshold.value == -math.inf
    assert threshold.is_good(-1e6)


def test_route_updates_offspring_by_offspring_as_algorithm_1():
    threshold = Threshold(0.9)
    threshold.observe(100.0)
    good = threshold.route(torch.tensor([95.0, 200.0, 95.0, 185.0]))
    # 95 >= 90 (best 100), then best 200 -> threshold 180: 95 bad, 185 good
    assert good.tolist() == [True, True, False, True]
    assert threshold.best == 200.0


def test_fraction_out_of_range_is_rejected():
    with pytest.raises(ValueError, match="threshold.fraction"):
        Threshold(1.5)


def test_state_round_trip():
    threshold = Threshold(0.8)
    threshold.observe(-3.0)
    restored = Threshold()
    restored.load_state_dict(threshold.state_dict())
    assert restored.value == threshold.value == pytest.approx(-3.6)
