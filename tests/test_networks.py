import copy

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from torchrl_esrl.envs import make_env
from torch import nn
from torchrl.modules import MLP

from torchrl_esrl.modules.networks import (
    Mirrored, PopulationActor, describe_actor, describe_mlp, flat_parameters, load_flat_parameters, make_actor, make_critic, one_blas_thread,
)


def test_actor_is_the_papers_2x256_tanh_network_within_bounds():
    env = make_env("halfcheetah")
    actor = make_actor(17, env.action_spec)
    linear = [m for m in actor.modules() if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linear] == [(17, 256), (256, 256), (256, 6)]
    assert any(isinstance(m, torch.nn.Tanh) for m in actor.modules())
    out = actor(TensorDict(observation=100 * torch.randn(64, 17), batch_size=[64]))["action"]
    assert env.action_spec.is_in(out)


def test_flat_parameters_round_trip_excludes_buffers():
    actor = make_actor(5, make_env("pendulum").action_spec, hidden=(8, 8))
    vector = flat_parameters(actor)
    assert vector.numel() == sum(p.numel() for p in actor.parameters())
    load_flat_parameters(actor, torch.arange(vector.numel(), dtype=torch.float32))
    assert torch.equal(flat_parameters(actor), torch.arange(vector.numel(), dtype=torch.float32))


def test_loaded_flat_parameters_are_views_of_the_vector_in_the_same_parameter_objects():
    """As its docstring says: the parameter objects stay, their data become views of the vector
    (writes to one show in the other), and a vector of another dtype is copied first."""
    actor = make_actor(5, make_env("pendulum").action_spec, hidden=(8, 8))
    parameters = list(actor.parameters())
    vector = torch.randn(sum(p.numel() for p in parameters))
    load_flat_parameters(actor, vector)
    assert list(actor.parameters()) == parameters and torch.equal(flat_parameters(actor), vector)
    vector.zero_()
    assert torch.equal(flat_parameters(actor), torch.zeros_like(vector))
    doubles = torch.ones(vector.numel(), dtype=torch.float64)
    load_flat_parameters(actor, doubles)
    doubles.zero_()
    assert torch.equal(flat_parameters(actor), torch.ones_like(vector))


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


def test_describe_mlp_reads_layers_biases_and_activations_or_says_why_not():
    """The one reading of a network that every fast piece decides from."""
    critic = make_critic(4, 2, (8, 6), "tanh")
    description = describe_mlp(critic.module)
    assert description.sizes == [(8, 6), (6, 8), (1, 6)]
    assert [layer.activation for layer in description.layers] == ["tanh", "tanh", None]
    assert [layer.name for layer in description.layers] == ["0", "2", "4"]
    assert description.plain_refusal() is None
    biasless = nn.Sequential(nn.Linear(4, 3, bias=False), nn.ReLU(), nn.Linear(3, 1))
    assert describe_mlp(biasless).plain_refusal() == "a Linear without bias"
    assert describe_mlp(nn.Sequential(nn.Linear(4, 3), nn.Linear(3, 1))).plain_refusal() == "two Linear layers without an activation between them"
    assert describe_mlp(nn.Sequential(nn.Linear(4, 3), nn.Tanh())).plain_refusal() == "an activation after the last Linear"
    assert describe_mlp(nn.Sequential(nn.Linear(4, 3), nn.ELU(), nn.Linear(3, 1))).startswith("ELU")
    assert describe_mlp(nn.Sequential(nn.Linear(4, 3), nn.Tanh(), nn.Tanh())) == "Tanh not right after a Linear"
    assert "reshaped" in describe_mlp(MLP(in_features=4, out_features=(2, 1), num_cells=[3]))
    assert "Sequential" in describe_mlp(type("Custom", (nn.Sequential,), {})(nn.Linear(4, 1)))
    env = make_env("pendulum")
    assert describe_actor(make_actor(3, env.action_spec)).mlp.sizes == [(256, 3), (256, 256), (1, 256)]
    assert describe_actor(critic).startswith("actor is not")


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


def _hooked(edit):
    actor = make_actor(3, make_env("pendulum").action_spec, (8, 8))
    edit(actor)
    return actor


def test_describe_actor_says_what_runs_beside_the_layers_classes():
    """Hooks that run in a forward, a forward set on an instance, parametrizations and parameters
    that are not the Linear layers' are refused by name; buffers and backward hooks (which a
    forward without gradient does not run) are not."""
    from torch.nn.modules import module as torch_module

    refused = {
        "a forward hook on module.0.module": lambda a: a[0].module.register_forward_hook(lambda m, args, out: out),
        "a forward pre hook on module.0.module.2": lambda a: a[0].module[2].register_forward_pre_hook(lambda m, args: None),
        "a forward pre hook on module.0.module.0": lambda a: torch.nn.utils.spectral_norm(a[0].module[0]),
        "a forward set on the instance module.1": lambda a: setattr(a[1], "forward", a[1].forward),
        "actor MLP: 0: a parametrization of its weight (torch.nn.utils.parametrize)": lambda a: torch.nn.utils.parametrizations.weight_norm(a[0].module[0]),
        "actor parameters other than its Linear layers' weights and biases (module.1.scale)": lambda a: a[1].register_parameter("scale", nn.Parameter(torch.ones(1))),
    }
    for reason, edit in refused.items():
        assert describe_actor(_hooked(edit)) == reason
    kept = [
        lambda a: a[0].module[0].register_buffer("scale", torch.ones(8)),
        lambda a: a[0].module[2].register_full_backward_hook(lambda m, grad_input, grad_output: None),
        lambda a: a[0].module.register_full_backward_pre_hook(lambda m, grad_output: None),
    ]
    for edit in kept:
        assert not isinstance(describe_actor(_hooked(edit)), str)
    for register, hook, reason in (
        (torch_module.register_module_forward_hook, lambda m, args, out: None, "torch's global forward hooks"),
        (torch_module.register_module_forward_pre_hook, lambda m, args: None, "torch's global forward pre hooks"),
    ):
        handle = register(hook)
        try:
            assert describe_actor(_hooked(lambda a: None)) == reason
        finally:
            handle.remove()
    assert PopulationActor.refusal(_hooked(lambda a: None)) is None


def test_own_actions_finds_what_is_not_a_function_of_the_observation_and_changes_nothing():
    """The probe calls a copy of the actor twice: random draws, calls that differ and a state the
    forward changes are named; the actor, its buffers and the global generators stay as they were."""
    import random

    from torchrl_esrl.modules.networks import nondeterminism, own_actions, probe_observations

    def count(module, args):
        module.calls.add_(1)

    def counting(actor):
        actor[0].module.register_buffer("calls", torch.zeros(()))
        actor[0].module.register_forward_pre_hook(count)

    cases = {
        "its forward draws random numbers": lambda a: a[0].module.insert(2, nn.Dropout(0.5)),
        "two calls on the same observation give different actions": lambda a: torch.nn.utils.spectral_norm(a[0].module[0]),
        "its forward changes module.0.module.calls": counting,
        None: lambda a: a[0].module.insert(2, nn.Dropout(0.5)).eval(),  # dropout in eval mode: the identity
    }
    for reason, edit in cases.items():
        actor = _hooked(edit)
        before = {k: v.clone() for k, v in actor.state_dict().items()}
        torch.manual_seed(3), np.random.seed(3), random.seed(3)
        states = torch.get_rng_state(), np.random.get_state()[1].copy(), random.getstate()
        assert nondeterminism(actor, 3) == reason
        assert torch.equal(torch.get_rng_state(), states[0]) and np.array_equal(np.random.get_state()[1], states[1]) and random.getstate() == states[2]
        assert all(torch.equal(before[k], v) for k, v in actor.state_dict().items())
    plain = _hooked(lambda a: None)
    with torch.no_grad():
        expected = plain(TensorDict(observation=probe_observations(3), batch_size=[4]))["action"]
    torch.testing.assert_close(own_actions(plain, probe_observations(3)), expected)


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
