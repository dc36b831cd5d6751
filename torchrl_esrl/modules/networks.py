"""Actor and critic networks of ES-TD3Buffers (paper, Section 4.2 "Architecture").

The actor is shared by both halves of the algorithm: TD3 trains it by gradient
descent, OpenAI-ES searches over its *flat parameter vector*. `flat_parameters`
and `load_flat_parameters` are the bridge between the two views (ES populations of many
flat vectors are evaluated in :mod:`torchrl_esrl.modules.population`). `describe_mlp` and
`describe_actor` are the one reading of a network that every hand-written (fast) piece decides
from: its layers, and what runs beside them (hooks, parametrizations, parameters); the probes
(`own_actions`, `forward_difference`, `nondeterminism`) then compare what a hand-written forward
gives with what the module itself gives on a few observations, and whether that is a
deterministic function of the observation.
"""
from __future__ import annotations

import copy
import random
from dataclasses import dataclass, replace

import numpy as np
import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from tensordict import TensorDict
from torch import nn
from torch.nn.utils import parameters_to_vector, parametrize, vector_to_parameters
from torchrl.data import TensorSpec
from torchrl.modules import MLP, TanhModule, ValueOperator

from torchrl_esrl.run.capacity import mlp_parameters
from torchrl_esrl.threads import torch_threads
from torchrl_esrl.torchrl_private import FORWARD_HOOK_KINDS, global_module_hooks, module_hook_dicts

ACTIVATIONS = {"tanh": nn.Tanh, "relu": nn.ReLU, "elu": nn.ELU}  # actor.activation, td3.critic_activation
# The activations the fast pieces compute, by module type (exact types); any other layer hands over to the reference.
FAST_ACTIVATIONS = {nn.Tanh: "tanh", nn.ReLU: "relu"}


def make_actor(
    observation_dim: int,
    action_spec: TensorSpec,
    hidden: tuple[int, ...] = (256, 256),
    activation: str = "tanh",
) -> TensorDictSequential:
    """Deterministic actor: MLP with tanh between all layers, squashed to the action bounds.

    Reads ``"observation"`` and writes ``"action"``; the bounds come from ``action_spec``
    through TorchRL's :class:`~torchrl.modules.TanhModule`.
    """
    mlp = MLP(
        in_features=observation_dim,
        out_features=action_spec.shape[-1],
        num_cells=list(hidden),
        activation_class=ACTIVATIONS[activation],
    )
    return TensorDictSequential(
        TensorDictModule(mlp, in_keys=["observation"], out_keys=["action_preactivation"]),
        TanhModule(in_keys=["action_preactivation"], out_keys=["action"], spec=action_spec),
    )


def squash(tanh_module: TanhModule, x: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """What TorchRL's ``TanhModule`` computes on ``x`` with bounds ``low``/``high`` (for the
    hand-written forwards of the TD3 loss and the TD3 collector)."""
    x = x.tanh()
    if tanh_module.clamp:
        eps = torch.finfo(x.dtype).resolution
        x = x.clamp(-1 + eps, 1 - eps)
    if tanh_module.non_trivial:
        x = low + (high - low) * (x + 1) / 2
    return x


def make_critic(
    observation_dim: int,
    action_dim: int,
    hidden: tuple[int, ...] = (256, 256),
    activation: str = "relu",
) -> ValueOperator:
    """Q(s, a): MLP over the concatenated observation and action (one output)."""
    mlp = MLP(
        in_features=observation_dim + action_dim,
        out_features=1,
        num_cells=list(hidden),
        activation_class=ACTIVATIONS[activation],
    )
    return ValueOperator(mlp, in_keys=["observation", "action"])


def flat_parameters(actor: nn.Module) -> torch.Tensor:
    """The actor's trainable parameters as one vector (buffers such as action bounds excluded)."""
    return parameters_to_vector(actor.parameters()).detach().clone()


@torch.no_grad()
def load_flat_parameters(actor: nn.Module, vector: torch.Tensor) -> None:
    """Load ``vector`` into the actor's parameters (``torch.nn.utils.vector_to_parameters``): each
    parameter object stays (optimiser references stay valid), its ``.data`` becomes a view of
    ``vector`` (of a copy where the dtype or device differ). The two share storage from then on: a
    write to either changes the other, so pass ``vector.clone()`` where the vector will be reused.
    The views are what :class:`~torchrl_esrl.modules.population.ModulePopulation` evaluates, bit for
    bit: a copy into storage of the parameters' own can round differently, as products may take
    another path on other alignments."""
    reference = next(actor.parameters())
    vector_to_parameters(vector.to(device=reference.device, dtype=reference.dtype), actor.parameters())


@dataclass(frozen=True)
class LinearLayer:
    """One ``nn.Linear`` of an MLP and the activation right after it (a name of
    :data:`FAST_ACTIVATIONS`, or None)."""

    name: str  # the child's name in the Sequential (its parameters' prefix)
    linear: nn.Linear
    activation: str | None = None


@dataclass(frozen=True)
class MLPDescription:
    """What a fast piece needs to reproduce an MLP: its Linear layers in order, each with its
    bias or not and the activation after it (:func:`describe_mlp`)."""

    layers: tuple[LinearLayer, ...]

    @property
    def sizes(self) -> list[tuple[int, int]]:
        """``(out_features, in_features)`` per Linear."""
        return [(layer.linear.out_features, layer.linear.in_features) for layer in self.layers]

    def plain_refusal(self) -> str | None:
        """None when every Linear has a bias and an activation sits between every two Linear
        layers and none after the last (``make_actor``, ``make_critic``), else what differs."""
        if any(layer.linear.bias is None for layer in self.layers):
            return "a Linear without bias"
        if any(layer.activation is None for layer in self.layers[:-1]):
            return "two Linear layers without an activation between them"
        if self.layers[-1].activation is not None:
            return "an activation after the last Linear"
        return None


def describe_mlp(module: nn.Module) -> MLPDescription | str:
    """``module`` as an :class:`MLPDescription` when it is an ``nn.Sequential`` (or TorchRL
    ``MLP``) of ``nn.Linear`` layers, each followed by at most one activation of
    :data:`FAST_ACTIVATIONS`; else the reason, in a few words (another layer, a reshaped output)."""
    if type(module) not in (nn.Sequential, MLP):
        return f"{type(module).__name__}, not nn.Sequential or TorchRL's MLP (its forward may differ)"
    if isinstance(getattr(module, "out_features", None), (tuple, list, torch.Size)):
        return "a reshaped output (out_features is a shape)"
    layers: list[LinearLayer] = []
    for name, child in module.named_children():
        if parametrize.is_parametrized(child):
            return f"{name}: a parametrization of its {', '.join(child.parametrizations)} (torch.nn.utils.parametrize)"
        if type(child) is nn.Linear:
            layers.append(LinearLayer(name, child))
        elif type(child) in FAST_ACTIVATIONS and layers and layers[-1].activation is None:
            layers[-1] = replace(layers[-1], activation=FAST_ACTIVATIONS[type(child)])
        elif type(child) in FAST_ACTIVATIONS:
            return f"{type(child).__name__} not right after a Linear"
        else:
            return f"{type(child).__name__} (the fast pieces compute Linear, {', '.join(c.__name__ for c in FAST_ACTIVATIONS)})"
    return MLPDescription(tuple(layers)) if layers else "no Linear layer"


@dataclass(frozen=True)
class ActorDescription:
    """A :func:`make_actor` actor as the fast pieces read it: its MLP and its ``TanhModule``."""

    mlp: MLPDescription
    tanh_module: TanhModule


def describe_actor(actor: nn.Module) -> ActorDescription | str:
    """``actor`` as an :class:`ActorDescription` when it computes what its modules' classes say:
    ``TensorDictModule(MLP, observation)`` then ``TanhModule -> action`` with an MLP
    :func:`describe_mlp` reads, whose parameters are its Linear layers' weights and biases (in
    order), with no forward hook or forward pre-hook (the module's own or torch's global ones) and
    no ``forward`` set on an instance; else the reason. Buffers are allowed: none of these
    classes' forwards reads a buffer but ``TanhModule``'s bounds. Backward hooks are allowed: a
    forward without gradient does not run them (the TD3 loss checks them itself)."""
    steps = actor.module if type(actor) is TensorDictSequential else ()
    if not (
        len(steps) == 2
        and type(steps[0]) is TensorDictModule
        and type(steps[1]) is TanhModule
        and list(steps[0].in_keys) == ["observation"]
        and list(steps[0].out_keys) == list(steps[1].in_keys)
        and len(steps[1].in_keys) == 1
        and list(steps[1].out_keys) == ["action"]
    ):
        return "actor is not TensorDictModule(MLP, observation) + TanhModule -> action"
    mlp = describe_mlp(steps[0].module)
    if isinstance(mlp, str):
        return f"actor MLP: {mlp}"
    reason = _call_refusal(actor)
    if reason is not None:
        return reason
    expected = [f"module.0.module.{layer.name}.{kind}" for layer in mlp.layers for kind, tensor in (("weight", layer.linear.weight), ("bias", layer.linear.bias)) if tensor is not None]
    names = [name for name, _ in actor.named_parameters()]
    if names != expected:
        other = next((name for name in names if name not in expected), None) or next(name for name in expected if name not in names)
        return f"actor parameters other than its Linear layers' weights and biases ({other})"
    return ActorDescription(mlp, steps[1])


def _call_refusal(module: nn.Module) -> str | None:
    """Why calling ``module`` may run more than its modules' classes' forwards: forward hooks or
    forward pre-hooks (its modules' or torch's global ones), a ``forward`` set on an instance."""
    for kind in FORWARD_HOOK_KINDS:
        if global_module_hooks((kind,)):
            return f"torch's global {kind.replace('_', ' ')} hooks"
    for name, child in module.named_modules():
        for kind in FORWARD_HOOK_KINDS:
            if any(module_hook_dicts((child,), (kind,))):
                return f"a {kind.replace('_', ' ')} hook on {name or 'the actor'}"
        if "forward" in vars(child):
            return f"a forward set on the instance {name or 'the actor'}"
    return None


# ------------------------------------------------------------------------ probes: what a module computes
PROBE_SCALES = (0.1, 1.0, 3.0, 10.0)  # the probe's observations: a standard normal row at each scale (MuJoCo's reach ~10)
PROBE_ATOL = 1e-4  # a hand-written forward's largest distance from the module's own, per unit of the action range


def probe_observations(observation_dim: int) -> torch.Tensor:
    """The few observations [4, observation_dim] the probes call actors on (a generator of their own:
    the run's random streams are not touched)."""
    rows = torch.randn(len(PROBE_SCALES), observation_dim, generator=torch.Generator().manual_seed(0))
    return rows * torch.tensor(PROBE_SCALES).unsqueeze(-1)


@torch.no_grad()
def own_actions(actor: nn.Module, observations: torch.Tensor) -> torch.Tensor | str:
    """The actions [N, act] ``actor``'s own forward gives on each of ``observations`` [N, obs]
    alone, as the reference evaluation calls it; or why they are not a deterministic function of
    the observation: the forward draws from a global random generator (torch's, numpy's or
    Python's: dropout, ``RReLU`` in training mode), two calls on the same observations differ, or
    a call changes the module's parameters or buffers (``spectral_norm``'s power iteration,
    running statistics). A copy of ``actor`` is called, twice, and the global generators are left
    as they were: the run is not changed by the probe."""
    try:
        probed = copy.deepcopy(actor)
    except Exception as error:  # noqa: BLE001 - a module that cannot be copied cannot be probed
        return f"it cannot be copied to be probed ({type(error).__name__})"
    states = _random_states()
    try:
        with torch_threads(1):  # as ModulePopulation calls it
            calls = [
                torch.cat([probed(TensorDict(observation=row.unsqueeze(0), batch_size=[1])).get("action") for row in observations])
                for _ in range(2)
            ]
    except Exception as error:  # noqa: BLE001 - whatever it raises, the reference raises it too
        return f"its forward fails on one observation ({type(error).__name__}: {str(error).strip().splitlines()[0] if str(error).strip() else ''})"
    finally:
        drew = _random_states() != states
        _restore_random_states(states)
    if drew:
        return "its forward draws random numbers"
    if not torch.equal(calls[0], calls[1]):
        return "two calls on the same observation give different actions"
    before, after = _tensors(actor), _tensors(probed)
    changed = next((name for name in before if name not in after or not torch.equal(before[name], after[name])), None)
    if changed is not None:
        return f"its forward changes {changed}"
    return calls[0]


def nondeterminism(actor: nn.Module, observation_dim: int) -> str | None:
    """Why ``actor`` is not a deterministic function of its observation (:func:`own_actions` on
    :func:`probe_observations`), or None."""
    actions = own_actions(actor, probe_observations(observation_dim))
    return actions if isinstance(actions, str) else None


def forward_difference(actor: nn.Module, forwards: dict, observations: torch.Tensor, span: torch.Tensor) -> str | None:
    """Why the hand-written ``forwards`` (name: observations [N, obs] -> actions [N, act]) do not
    compute what ``actor`` computes on ``observations`` (:func:`own_actions`, up to float32
    rounding: :data:`PROBE_ATOL` per unit of ``span``, the action range), or None."""
    expected = own_actions(actor, observations)
    if isinstance(expected, str):
        return f"actor: {expected}"
    atol = PROBE_ATOL * max(1.0, float(span.max()))
    for name, forward in forwards.items():
        got = forward(observations)
        if got.shape != expected.shape or not torch.allclose(got.to(expected.dtype), expected, rtol=0, atol=atol):
            gap = (got.double() - expected.double()).abs().max().item() if got.shape == expected.shape else float("nan")
            return f"{name} gives actions {gap:.3g} away from the actor's own forward"
    return None


def _tensors(module: nn.Module) -> dict[str, torch.Tensor]:
    """``module``'s parameters and buffers by name."""
    return {name: tensor.detach() for name, tensor in (*module.named_parameters(), *module.named_buffers())}


class _RandomStates(tuple):
    """The global generators' states: torch's (CPU), numpy's and Python's; equal when no draw was made."""

    def __eq__(self, other) -> bool:
        (torch_a, numpy_a, python_a), (torch_b, numpy_b, python_b) = self, other
        return (
            torch.equal(torch_a, torch_b)
            and numpy_a[0] == numpy_b[0] and np.array_equal(numpy_a[1], numpy_b[1]) and numpy_a[2:] == numpy_b[2:]
            and python_a == python_b
        )

    def __ne__(self, other) -> bool:
        return not self == other

    __hash__ = None


def _random_states() -> _RandomStates:
    return _RandomStates((torch.get_rng_state(), np.random.get_state(), random.getstate()))


def _restore_random_states(states: _RandomStates) -> None:
    torch.set_rng_state(states[0])
    np.random.set_state(states[1])
    random.setstate(states[2])


# ------------------------------------------------------------ built from the config (recipes)
NETWORK_FIELD = "actor.hidden or td3.critic_hidden"  # what a refusal for the networks' memory names


def make_actor_critic(cfg, env):
    """The paper's actor (2x256 tanh, ``actor``) and the critic template TD3 duplicates into twin
    critics (``td3.critic_hidden``, ``td3.critic_activation``), on ``cfg.device`` (TD3's side; ES
    evaluates populations on CPU, see :func:`cpu_actor`)."""
    observation_dim = env.observation_spec["observation"].shape[-1]
    action_dim = env.action_spec.shape[-1]
    actor = make_actor(observation_dim, env.action_spec, tuple(cfg.actor.hidden), cfg.actor.activation)
    critic = make_critic(observation_dim, action_dim, tuple(cfg.td3.critic_hidden), cfg.td3.critic_activation)
    return actor.to(cfg.device), critic.to(cfg.device)


def cpu_actor(actor):
    """``actor`` itself on CPU, else a CPU copy: the template of ES populations and evaluations,
    whose physics (and batched forward) run on CPU whatever device TD3 trains on."""
    if all(p.device.type == "cpu" for p in actor.parameters()):
        return actor
    return copy.deepcopy(actor).to("cpu")


def actor_parameters(cfg, sizes) -> int:
    """The number of parameters of :func:`make_actor_critic`'s actor for a task of ``sizes`` (:class:`~torchrl_esrl.envs.EnvSizes`)."""
    return mlp_parameters([sizes.observation_dim, *cfg.actor.hidden, sizes.action_dim])
