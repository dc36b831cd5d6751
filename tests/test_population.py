import copy

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from torchrl_esrl.envs import make_env
from torch import nn

from torchrl_esrl.modules.networks import describe_actor, flat_parameters, load_flat_parameters, make_actor
from torchrl_esrl.modules.population import Mirrored, PopulationActor, one_blas_thread


def _batched_equals_each_member(actor, members: int) -> torch.Tensor:
    """PopulationActor's actions for ``members`` perturbed actors, checked against each one loaded
    into the actor module; returns them."""
    population = flat_parameters(actor)[None] + 0.3 * torch.randn(members, flat_parameters(actor).numel())
    observations = torch.randn(members, 3)
    batched = PopulationActor(actor)(population, observations)
    member = copy.deepcopy(actor)
    for p in range(members):
        load_flat_parameters(member, population[p])
        expected = member(TensorDict(observation=observations[p : p + 1], batch_size=[1]))["action"]
        torch.testing.assert_close(batched[p : p + 1], expected, rtol=1e-5, atol=1e-6)
    return batched


def test_population_actor_matches_each_member_loaded_into_the_actor():
    env = make_env("pendulum")  # action bounds [-2, 2]: checks the rescaling too
    actor = make_actor(3, env.action_spec)
    batched = _batched_equals_each_member(actor, members=6)
    assert batched.abs().max() <= 2.0 and batched.abs().max() > 1.0


def test_population_actor_computes_mixed_activations_and_refuses_a_biasless_linear():
    env = make_env("pendulum")
    actor = make_actor(3, env.action_spec, (16, 16), "tanh")
    actor[0].module[3] = nn.ReLU()  # tanh after the first Linear, ReLU after the second
    _batched_equals_each_member(actor, members=4)
    actor[0].module[2] = nn.Linear(16, 16, bias=False)  # its flat vector has no bias to split
    assert PopulationActor.refusal(actor) == "actor MLP: a Linear without bias"
    with pytest.raises(ValueError, match="ModulePopulation"):
        PopulationActor(actor)


def test_population_actor_gives_a_block_of_members_the_actions_of_the_whole_population():
    # The overlapped ES rollout evaluates each half of the population on its own
    # (torchrl_esrl/collectors/mujoco_batch.py): its members must get bit for bit the
    # actions the forward over all P gives them.
    actor = make_actor(17, make_env("halfcheetah").action_spec)
    population = flat_parameters(actor)[None] + 0.005 * torch.randn(120, flat_parameters(actor).numel())
    observations = torch.randn(120, 17)
    policy = PopulationActor(actor)
    whole = policy(population, observations)
    for block in (slice(0, 60), slice(60, 120), slice(7, 8), slice(1, 120)):
        assert torch.equal(policy(population[block], observations[block]), whole[block])


def test_mirrored_forward_gives_each_pair_the_actions_of_its_two_rows():
    """PopulationActor.mirrored on center +- offsets equals the forward over the flat rows up to
    float32 rounding, and a block of pairs gets bit for bit the actions of all pairs."""
    actor = make_actor(17, make_env("halfcheetah").action_spec)
    center = flat_parameters(actor)
    offsets = 0.05 * torch.randn(30, center.numel(), generator=torch.Generator().manual_seed(1))
    mirrored = Mirrored(center, offsets)
    params = torch.cat([center + offsets, center - offsets])
    assert mirrored.matches(params) and not mirrored.matches(params.flip(0))
    observations = torch.randn(60, 17, generator=torch.Generator().manual_seed(2))
    policy = PopulationActor(actor)
    pairs = policy.mirrored(*policy.split_pairs(mirrored), observations.numpy().reshape(2, 30, 17))
    torch.testing.assert_close(torch.from_numpy(pairs.reshape(60, -1)), policy(params, observations), rtol=1e-5, atol=1e-6)
    for block in (slice(10, 20), slice(0, 2), slice(28, 30), slice(0, 16)):  # any block size: the same products per pair
        part = policy.mirrored(*policy.split_pairs(mirrored, block), observations.numpy().reshape(2, 30, 17)[:, block])
        assert np.array_equal(part, pairs[:, block]), block


def test_one_blas_thread_holds_numpy_blas_at_one_thread_and_restores_it():
    from threadpoolctl import threadpool_info

    def openblas_threads():
        return [lib["num_threads"] for lib in threadpool_info() if lib["internal_api"] == "openblas"]

    before = openblas_threads()
    if not before:
        pytest.skip("numpy's BLAS is not OpenBLAS in this install")
    with one_blas_thread():
        assert all(n == 1 for n in openblas_threads())
    assert openblas_threads() == before


@pytest.mark.parametrize("observation_dim", [1, 17, 18, 105, 348])
def test_population_actor_equals_the_module_per_step_for_any_observation_width(observation_dim):
    """The batched forward, over the flat rows and over mirrored pairs, gives every member the
    actions of the actor module loaded with its parameters up to float32 rounding, whatever the
    observation's width (HalfCheetah's 17, 18 with its x position, Ant's 105, Humanoid's 348).
    Returns of whole episodes can differ by more: a step's rounding grows in closed loop."""
    actor = make_actor(observation_dim, make_env("halfcheetah").action_spec)
    center = flat_parameters(actor)
    offsets = 0.05 * torch.randn(3, center.numel(), generator=torch.Generator().manual_seed(1))
    params = torch.cat([center + offsets, center - offsets])
    observations = 3 * torch.randn(6, observation_dim, generator=torch.Generator().manual_seed(2))
    policy = PopulationActor(actor)
    flat = policy(params, observations)
    with one_blas_thread():
        pairs = torch.from_numpy(policy.mirrored(*policy.split_pairs(Mirrored(center, offsets)), observations.numpy().reshape(2, 3, -1)).reshape(6, -1))
    member = copy.deepcopy(actor)
    for p in range(6):
        load_flat_parameters(member, params[p].clone())
        with torch.no_grad():
            expected = member(TensorDict(observation=observations[p : p + 1], batch_size=[1]))["action"]
        torch.testing.assert_close(flat[p : p + 1], expected, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(pairs[p : p + 1], expected, rtol=1e-5, atol=1e-6)


def test_the_comparison_finds_what_the_description_misses(monkeypatch):
    """A forward the description cannot see (here ``nn.Linear.forward`` itself replaced): the
    batched forward against the module's own on the probe's observations refuses it."""
    actor = make_actor(3, make_env("pendulum").action_spec, (8, 8))
    assert PopulationActor.refusal(actor) is None
    monkeypatch.setattr(nn.Linear, "forward", lambda self, x: torch.nn.functional.linear(x, self.weight, self.bias) * 0.5)
    assert not isinstance(describe_actor(actor), str)
    reason = PopulationActor.refusal(actor)
    assert reason.startswith("the batched forward gives actions") and reason.endswith("away from the actor's own forward"), reason
    with pytest.raises(ValueError, match="away from the actor's own forward"):
        PopulationActor(actor)
