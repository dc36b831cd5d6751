"""The ES phase's population step between ask and evaluation (ERL's injection), inline and in the
background (``es.schedule=async``); the phase resumed from the generations a checkpoint holds."""
import numpy as np
import pytest
import torch

from torchrl_esrl.algorithm.es_phase import ESPhase, GenerationsDone, es_phase
from torchrl_esrl.collectors.es_collector import ESCollector
from torchrl_esrl.data.multibuffer import MultiBuffer
from torchrl_esrl.data.threshold import Threshold
from torchrl_esrl.envs import make_env
from torchrl_esrl.es.ga import GeneticAlgorithm
from torchrl_esrl.es.openes import OpenES
from torchrl_esrl.modules.networks import flat_parameters, make_actor

MEMBERS, STEPS, SEED, GENERATIONS = 4, 30, 3, 2


def parts():
    torch.manual_seed(0)
    actor = make_actor(8, make_env("swimmer").action_spec, (16, 16))
    collector = ESCollector("swimmer", actor, backend="gym", max_episode_steps=STEPS, seed=SEED)
    buffer = MultiBuffer(ratio=(0.5, 0.5, 0.0), capacity=1000, batch_size=8, min_size=8)
    return actor, collector, buffer, Threshold(0.9)


def known_vector(actor):
    """Another actor's parameters: the member a step writes into row 0."""
    torch.manual_seed(7)
    return flat_parameters(make_actor(8, make_env("swimmer").action_spec, (16, 16)))


def first_member_seeds():
    """The episode seed of member 0 in each generation: the ES collector's stream (seed ``SEED``, one seed per member)."""
    stream = np.random.default_rng(SEED)
    return [int(stream.integers(0, 2**31 - 1, size=MEMBERS)[0]) for _ in range(GENERATIONS)]


@pytest.mark.parametrize("background", [False, True], ids=["sequential", "async"])
@pytest.mark.parametrize("in_place", [True, False], ids=["written in place", "returned"])
def test_a_step_that_writes_a_known_vector_into_row_0_makes_that_member_play_it(background, in_place):
    actor, collector, buffer, threshold = parts()
    vector = known_vector(actor)
    ga = GeneticAlgorithm.for_actor(actor, MEMBERS, torch.Generator().manual_seed(1), elite_fraction=0.25)
    seen = []

    def write_row_0(population, generation):
        seen.append(generation)
        if not in_place:
            population = population.clone()
        population[0] = vector
        return None if in_place else population

    phase = ESPhase(ga, collector, buffer, threshold, GENERATIONS, shared_buffer=False, background=background, population_step=write_row_0)
    phase.start()
    returns = phase.finish().returns
    phase.close()

    assert seen == [0, 1]  # the generation count of each asked population (es.generation, checkpointed with the GA)
    reference = ESCollector("swimmer", actor, backend="gym", max_episode_steps=STEPS)
    played = [reference.evaluate(vector, seeds=[seed]).returns[0].item() for seed in first_member_seeds()]
    assert [r[0].item() for r in returns] == played
    assert played[0] not in returns[0][1:].tolist()  # not what another member scored
    assert torch.equal(ga.returns, returns[-1])  # the GA was told the population as evaluated
    sizes = phase.buffer.sizes()
    assert sizes["good"] + sizes["bad"] == GENERATIONS * MEMBERS * STEPS and sizes["noisy"] == 0  # every episode routed


def test_the_two_modes_give_the_same_generations_with_a_step():
    results = []
    for background in (False, True):
        actor, collector, buffer, threshold = parts()
        vector = known_vector(actor)
        ga = GeneticAlgorithm.for_actor(actor, MEMBERS, torch.Generator().manual_seed(1), elite_fraction=0.25)

        def inject_once_told(population, generation, ga=ga, vector=vector):  # ERL's injection over the weakest member
            if generation:
                ga.inject(population, vector)

        phase = ESPhase(ga, collector, buffer, threshold, GENERATIONS, shared_buffer=False, background=background, population_step=inject_once_told)
        phase.start()
        results.append((torch.cat(phase.finish().returns), ga.population.clone(), phase.buffer.sizes()))
        phase.close()
    (returns, population, sizes), (async_returns, async_population, async_sizes) = results
    assert torch.equal(returns, async_returns) and torch.equal(population, async_population) and sizes == async_sizes


def test_a_step_that_changes_nothing_leaves_openai_es_as_without_one():
    results = []
    for step in (None, lambda population, generation: None):
        actor, collector, buffer, threshold = parts()
        es = OpenES(flat_parameters(actor), population_size=MEMBERS, sigma=0.05, lr=0.01, generator=torch.Generator().manual_seed(1))
        returns = es_phase(es, collector, buffer, threshold, GENERATIONS, population_step=step)
        results.append((torch.cat(returns), es.mean.detach().clone()))
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])


def test_openai_es_refuses_a_population_its_noise_did_not_make():
    actor, collector, buffer, threshold = parts()
    es = OpenES(flat_parameters(actor), population_size=MEMBERS, sigma=0.05, lr=0.01)

    def write_row_0(population, generation):
        population[0] = known_vector(actor)

    with pytest.raises(ValueError, match="not the one the last ask returned"):
        es_phase(es, collector, buffer, threshold, 1, population_step=write_row_0)


def test_a_phase_resumed_after_its_first_generation_plays_the_rest_and_returns_all():
    actor, collector, buffer, threshold = parts()
    es = OpenES(flat_parameters(actor), population_size=MEMBERS, sigma=0.05, lr=0.01, generator=torch.Generator().manual_seed(1))
    seen = []
    first = GenerationsDone(returns=[torch.arange(float(MEMBERS))], work=5)
    at = GenerationsDone()
    at.load_state_dict(first.state_dict())  # as a checkpoint holds it
    assert torch.equal(at.returns[0], first.returns[0]) and at.work == 5
    returns = es_phase(es, collector, buffer, threshold, 3, on_generation=seen.append, at=at)
    assert seen == [1, 2] and es.generation == 2  # two generations played: the first was the checkpoint's
    assert len(returns) == 3 and torch.equal(returns[0], first.returns[0])
    assert at.returns == [] and at.work == 7  # the next iteration's phase starts from none; the run's count goes on
    empty = GenerationsDone()
    empty.load_state_dict(GenerationsDone().state_dict())
    assert empty.returns == [] and empty.work == 0
