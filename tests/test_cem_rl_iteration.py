import torch

from torchrl_esrl.algorithm.cem_rl_iteration import one_buffer, routed_by_return
from torchrl_esrl.collectors.es_collector import ESCollector
from torchrl_esrl.data.multibuffer import MultiBuffer
from torchrl_esrl.data.threshold import Threshold
from torchrl_esrl.envs import make_env
from torchrl_esrl.es.cem import DiagonalCEM
from torchrl_esrl.modules.networks import flat_parameters, make_actor


def _generation(members: int = 6, steps: int = 30):
    env = make_env("swimmer", max_episode_steps=steps)
    actor = make_actor(8, env.action_spec, (16, 16))
    cem = DiagonalCEM(flat_parameters(actor), population_size=members, sigma_init=0.5, generator=torch.Generator().manual_seed(3))
    return ESCollector("swimmer", actor, backend="gym", max_episode_steps=steps).evaluate(cem.ask())


def _buffer():
    return MultiBuffer(ratio=(0.5, 0.2, 0.3), capacity=1000, batch_size=8, min_size=8)


def test_rl_members_go_to_noisy_and_cem_members_to_good_or_bad_by_the_threshold():
    generation = _generation()
    returns, lengths = generation.returns, generation.lengths
    threshold, buffer = Threshold(0.9), _buffer()
    routed_by_return(threshold, rl_members=2)(generation, buffer)
    assert threshold.best == returns.max().item()  # every member's return counts towards the best, RL members' too
    expected = Threshold(0.9)
    for r in returns[:2].tolist():
        expected.observe(r)
    good = expected.route(returns[2:])  # CEM members in order, after the RL members raised the best
    sizes = buffer.sizes()
    assert sizes["noisy"] == int(lengths[:2].sum())
    assert sizes["good"] == int(lengths[2:][good].sum()) and sizes["bad"] == int(lengths[2:][~good].sum())
    assert sizes["good"] + sizes["bad"] + sizes["noisy"] == generation.frames


def test_one_buffer_is_cem_rl_every_episode_into_noisy():
    generation = _generation()
    buffer = _buffer()
    one_buffer(generation, buffer)
    assert buffer.sizes() == {"good": 0, "bad": 0, "noisy": generation.frames}
