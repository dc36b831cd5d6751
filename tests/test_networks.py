import numpy as np
import torch
from tensordict import TensorDict

from torchrl_esrl.envs import make_env
from torch import nn
from torchrl.modules import MLP

from torchrl_esrl.modules.networks import describe_actor, describe_mlp, flat_parameters, load_flat_parameters, make_actor, make_critic
from torchrl_esrl.modules.population import PopulationActor


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
