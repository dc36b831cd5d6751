import pytest
import torch

from torchrl_esrl.es.openes import OpenES, centered_ranks


def test_centered_ranks_span_minus_half_to_half_and_keep_order():
    shaped = centered_ranks(torch.tensor([10.0, -5.0, 3.0, 100.0]))
    assert shaped.tolist() == pytest.approx([1 / 6, -0.5, -1 / 6, 0.5])
    assert shaped.sum().item() == pytest.approx(0.0, abs=1e-6)


def test_ask_samples_antithetic_pairs_around_the_mean():
    es = OpenES(torch.ones(7), population_size=6, sigma=0.1, generator=torch.Generator().manual_seed(0))
    population = es.ask()
    assert population.shape == (6, 7)
    assert torch.allclose((population[:3] + population[3:]) / 2, torch.ones(7))
    assert not torch.allclose(population[0], population[1])


def test_es_update_improves_a_known_objective():
    target = torch.linspace(-1, 1, 50)

    def fitness(population):
        return -((population - target) ** 2).sum(dim=1)

    es = OpenES(torch.zeros(50), population_size=40, sigma=0.05, lr=0.05, generator=torch.Generator().manual_seed(0))
    start = fitness(es.mean.detach()[None]).item()
    for _ in range(300):
        population = es.ask()
        es.tell(population, fitness(population))
    end = fitness(es.mean.detach()[None]).item()
    assert end > 0.1 * start  # squared distance shrunk by more than 10x
    assert end > start


def test_gradient_points_uphill_on_a_linear_objective():
    direction = torch.randn(20, generator=torch.Generator().manual_seed(3))
    es = OpenES(torch.zeros(20), population_size=200, sigma=0.1, generator=torch.Generator().manual_seed(0))
    population = es.ask()
    grad = es.gradient(population @ direction)
    cosine = torch.nn.functional.cosine_similarity(grad, direction, dim=0)
    assert cosine > 0.7


def test_invalid_settings_are_rejected():
    with pytest.raises(ValueError, match="even"):
        OpenES(torch.zeros(3), population_size=5)
    with pytest.raises(ValueError, match="sigma"):
        OpenES(torch.zeros(3), sigma=0.0)


def test_non_finite_return_stops_the_update():
    es = OpenES(torch.zeros(3), population_size=4)
    population = es.ask()
    with pytest.raises(FloatingPointError, match="non-finite"):
        es.tell(population, torch.tensor([1.0, float("nan"), 0.0, 2.0]))


def test_set_mean_copies_and_can_reset_adam():
    es = OpenES(torch.zeros(5), population_size=4)
    es.tell(es.ask(), torch.arange(4.0))
    assert es.optimizer.state
    es.set_mean(torch.full((5,), 3.0), reset_optimizer=True)
    assert torch.equal(es.mean.detach(), torch.full((5,), 3.0))
    assert not es.optimizer.state


def test_state_dict_round_trip_continues_identically():
    a = OpenES(torch.zeros(5), population_size=4, generator=torch.Generator().manual_seed(1))
    a.tell(a.ask(), torch.arange(4.0))
    b = OpenES(torch.ones(5), population_size=4, generator=torch.Generator().manual_seed(9))
    b.load_state_dict(a.state_dict())
    assert torch.equal(a.ask(), b.ask())


def test_mirrored_is_the_asked_population_as_pairs():
    es = OpenES(torch.randn(9), population_size=6, sigma=0.01, generator=torch.Generator().manual_seed(0))
    population = es.ask()
    mirrored = es.mirrored(population)
    assert mirrored.offsets.shape == (3, 9)
    assert torch.equal(population, torch.cat([mirrored.center + mirrored.offsets, mirrored.center - mirrored.offsets]))
    assert es.mirrored(population.clone()) is not None  # the same rows
    assert es.mirrored(population.flip(0)) is None  # another population: its rows, flat
    es.tell(population, torch.arange(6.0))
    assert es.mirrored(population) is None  # told: no population is pending
    plain = OpenES(torch.zeros(3), population_size=3, antithetic=False)
    assert plain.mirrored(plain.ask()) is None


def test_tell_refuses_a_population_that_was_not_asked():
    """OpenAI-ES estimates its gradient from the noise it drew: told another population (edited
    rows, as CEM-RL's RL half makes), it refuses instead of ignoring the edit."""
    es = OpenES(torch.zeros(4), population_size=4, generator=torch.Generator().manual_seed(0))
    population = es.ask()
    edited = population.clone()
    edited[0] += 1.0
    with pytest.raises(ValueError, match="not the one the last ask returned"):
        es.tell(edited, torch.arange(4.0))
    es.tell(population.clone(), torch.arange(4.0))  # equal rows are the asked population
    assert es.generation == 1
