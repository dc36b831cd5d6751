import pytest
import torch

from torchrl_esrl.errors import ConfigError
from torchrl_esrl.envs import make_env
from torchrl_esrl.collectors.es_collector import ESCollector
from torchrl_esrl.modules.networks import flat_parameters, make_actor
from torchrl_esrl.modules.population import Mirrored


@pytest.fixture(scope="module")
def walker():
    actor = make_actor(17, make_env("walker2d").action_spec)
    return actor, ESCollector("walker2d", actor, backend="gym", max_episode_steps=200, seed=0)


def population(actor, size, scale):
    generator = torch.Generator().manual_seed(0)
    mean = flat_parameters(actor)
    return mean + scale * torch.randn(size, mean.numel(), generator=generator)


def test_generation_layout_and_tags(walker):
    actor, collector = walker
    generation = collector.evaluate(population(actor, 6, 0.1), seeds=list(range(6)))
    td = generation.transitions
    assert generation.returns.shape == (6,) and generation.lengths.shape == (6,)
    assert td.batch_size == torch.Size([generation.frames])
    for key, shape, dtype in [
        ("observation", (17,), torch.float32),
        ("action", (6,), torch.float32),
        (("next", "observation"), (17,), torch.float32),
        (("next", "reward"), (1,), torch.float32),
        (("next", "done"), (1,), torch.bool),
        (("next", "terminated"), (1,), torch.bool),
        (("next", "truncated"), (1,), torch.bool),
        ("episode_return", (1,), torch.float32),
    ]:
        assert td.get(key).shape[1:] == shape and td.get(key).dtype == dtype, key
    members = td["collector", "traj_ids"]
    for p in range(6):
        mine = td[members == p]
        assert mine.batch_size[0] == generation.lengths[p]
        assert mine["next", "reward"].sum().item() == pytest.approx(generation.returns[p].item(), rel=1e-4, abs=1e-3)
        assert torch.all(mine["episode_return"] == mine["episode_return"][0])
        assert mine["next", "done"][-1].item() and not mine["next", "done"][:-1].any()
        # consecutive: next observation of step t is the observation of step t+1
        torch.testing.assert_close(mine["next", "observation"][:-1], mine["observation"][1:])


def test_members_that_fall_stop_early_and_contribute_only_real_steps(walker):
    actor, collector = walker
    generation = collector.evaluate(population(actor, 8, 0.5), seeds=list(range(8)))
    assert generation.lengths.min() < 200  # some walkers fell
    terminated = generation.transitions["next", "terminated"].squeeze(-1)
    assert terminated.sum() == (generation.lengths < 200).sum()
    assert generation.frames == generation.lengths.sum()


def test_same_seeds_same_returns_and_mask_selects_members(walker):
    actor, collector = walker
    params = population(actor, 4, 0.1)
    first = collector.evaluate(params, seeds=[1, 2, 3, 4])
    second = collector.evaluate(params, seeds=[1, 2, 3, 4])
    assert torch.equal(first.returns, second.returns)
    chosen = torch.tensor([True, False, False, True])
    selected = first.transitions[first.member_mask(chosen)]
    assert selected.batch_size[0] == int(first.lengths[chosen].sum())


def test_frames_count_es_but_not_evaluation(walker):
    actor, collector = walker
    before = collector.frames
    generation = collector.evaluate(population(actor, 2, 0.1))
    assert collector.frames == before + generation.frames
    collector.evaluate_policy(flat_parameters(actor), 2)
    assert collector.frames == before + generation.frames


def test_unknown_backend_is_a_config_error():
    actor = make_actor(8, make_env("swimmer").action_spec)
    with pytest.raises(ConfigError, match="es.backend"):
        ESCollector("swimmer", actor, backend="warp")


def test_unknown_env_suggests_the_closest():
    actor = make_actor(8, make_env("swimmer").action_spec)
    with pytest.raises(ConfigError, match="did you mean 'walker2d'"):
        ESCollector("walker2", actor)


def test_mirrored_that_is_not_the_population_is_refused(walker):
    actor, collector = walker
    params = population(actor, 4, 0.1)
    with pytest.raises(ValueError, match="mirrored"):
        collector.evaluate(params, seeds=list(range(4)), mirrored=Mirrored(params[0], params[:2] - params[0]))


def test_members_of_a_generation_are_a_generation_of_their_own(walker):
    actor, collector = walker
    generation = collector.evaluate(population(actor, 5, 0.3), seeds=list(range(5)))
    part = generation.members(2, 4)
    assert torch.equal(part.returns, generation.returns[2:4]) and torch.equal(part.lengths, generation.lengths[2:4])
    expected = generation.transitions[generation.member_mask(torch.tensor([False, False, True, True, False]))]
    assert torch.equal(part.transitions["observation"], expected["observation"])
    assert torch.equal(part.transitions["collector", "traj_ids"], expected["collector", "traj_ids"] - 2)
    assert generation.transitions["collector", "traj_ids"].max() == 4  # the whole generation is left as it was
