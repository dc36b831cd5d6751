"""CEM-RL's diagonal CEM update (Pourchot and Sigaud 2019) and its TD3 member step."""
import math

import pytest
import torch

from torchrl_esrl.es.cem import DiagonalCEM, elite_weights


def test_elite_weights_are_log_rank_weights_summing_to_one():
    w = elite_weights(5)
    expected = torch.tensor([math.log(6 / i) for i in range(1, 6)])
    assert torch.allclose(w, expected / expected.sum())
    assert torch.all(w[:-1] > w[1:])  # better rank, larger weight


def test_tell_uses_top_half_for_mean_and_variance_around_old_mean():
    cem = DiagonalCEM(torch.zeros(3), population_size=4, sigma_init=0.1, damping_init=1e-3, damping_end=1e-5, damping_tau=0.5)
    population = torch.tensor([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [3.0, 1.0, 0.0], [4.0, 0.0, 2.0]])
    returns = torch.tensor([10.0, -5.0, 30.0, 0.0])  # elites: member 2 (best), then member 0
    elites = cem.tell(population, returns)
    assert elites.tolist() == [2, 0]
    w = elite_weights(2)  # [log(3), log(1.5)] normalised
    expected_mean = w[0] * population[2] + w[1] * population[0]
    assert torch.allclose(cem.mean, expected_mean)
    # variance around the OLD mean (0), plus the damping before its decay
    expected_var = w[0] * population[2] ** 2 + w[1] * population[0] ** 2 + 1e-3
    assert torch.allclose(cem.var, expected_var)
    assert cem.damping == pytest.approx(0.5 * 1e-3 + 0.5 * 1e-5)
    # the losers (members 1 and 3) did not move anything: coordinate 2 only in member 3
    assert cem.mean[2] == 0 and cem.var[2] == pytest.approx(1e-3)


def test_ask_samples_the_diagonal_gaussian():
    cem = DiagonalCEM(torch.full((2,), 5.0), population_size=4000, sigma_init=0.5, generator=torch.Generator().manual_seed(1))
    cem.var = torch.tensor([0.25, 4.0])
    samples = cem.ask()
    assert samples.shape == (4000, 2)
    assert torch.allclose(samples.mean(0), torch.tensor([5.0, 5.0]), atol=0.1)
    assert torch.allclose(samples.std(0), torch.tensor([0.5, 2.0]), rtol=0.05)


def test_cem_climbs_a_quadratic():
    target = torch.linspace(-1, 1, 8)
    cem = DiagonalCEM(torch.zeros(8), population_size=20, sigma_init=0.5, damping_init=1e-2, generator=torch.Generator().manual_seed(0))
    start = (cem.mean - target).norm()
    for _ in range(60):
        population = cem.ask()
        cem.tell(population, -((population - target) ** 2).sum(1))
    assert (cem.mean - target).norm() < 0.1 * start
