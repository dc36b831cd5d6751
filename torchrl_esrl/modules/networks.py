"""Actor and critic networks of ES-TD3Buffers (paper, Section 4.2 "Architecture").

The actor is shared by both halves of the algorithm: TD3 trains it by gradient
descent, OpenAI-ES searches over its *flat parameter vector*. `flat_parameters`
and `load_flat_parameters` are the bridge between the two views. Two classes evaluate
many flat vectors at once: `ModulePopulation` (the reference: the actor module itself,
through ``torch.func.functional_call``) and `PopulationActor` (one batched numpy forward
for a whole ES population, for the plain MLP actors of `make_actor`). `describe_mlp` and
`describe_actor` are the one reading of a network's layers that every hand-written (fast) piece
decides from.
"""
from __future__ import annotations

import copy
import threading
from dataclasses import dataclass, replace

import numpy as np
import torch
from threadpoolctl import ThreadpoolController
from tensordict.nn import TensorDictModule, TensorDictSequential
from tensordict import TensorDict
from torch import nn
from torch.func import functional_call
from torch.nn.utils import parameters_to_vector, vector_to_parameters
from torchrl.data import TensorSpec
from torchrl.modules import MLP, TanhModule, ValueOperator

from torchrl_esrl.run.capacity import mlp_parameters
from torchrl_esrl.threads import torch_threads

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
    The views are what :class:`ModulePopulation` evaluates, bit for bit: a copy into storage of the
    parameters' own can round differently, as products may take another path on other alignments."""
    reference = next(actor.parameters())
    vector_to_parameters(vector.to(device=reference.device, dtype=reference.dtype), actor.parameters())


@dataclass(frozen=True)
class Mirrored:
    """A population of mirrored pairs (the antithetic sampling of the paper's Section 5 and of
    Salimans et al. 2017): member ``k`` is ``center + offsets[k]`` and member ``K + k`` is
    ``center - offsets[k]``, K = ``len(offsets)``.

    What OpenAI-ES asks for (:meth:`torchrl_esrl.es.openes.OpenES.mirrored`), told to the
    evaluation backends so that each pair's offsets are read once per step for both members
    (:meth:`PopulationActor.mirrored`); the flat rows stay the reference.
    """

    center: torch.Tensor  # [D]
    offsets: torch.Tensor  # [K, D]

    def matches(self, params: torch.Tensor) -> bool:
        """Whether ``params`` [2K, D] has this structure (checked on the first pair, exactly)."""
        k = self.offsets.shape[0]
        if params.shape != (2 * k, self.center.numel()) or k == 0:
            return False
        return torch.equal(params[0], self.center + self.offsets[0]) and torch.equal(params[k], self.center - self.offsets[0])


class ModulePopulation:
    """The reference evaluation of ES members: the very actor module TD3 trains, run with each
    member's flat parameters through ``torch.func.functional_call`` (paper, Section 3: ES searches
    over the actor's flat parameters).

    ``actions = population(params[P, D], observations[P, obs_dim])``: member ``p`` acts as
    ``actor`` would after ``load_flat_parameters(actor, params[p])``, on a batch of one
    observation, whatever the actor's layers. The interface of :class:`PopulationActor`
    (``split``, ``num_parameters``), without its mirrored-pairs forward.
    """

    mirrored_pairs = False  # evaluates the flat rows only

    def __init__(self, actor: nn.Module):
        self.actor = actor
        # functional_call swaps the members' tensors into the one module: one forward at a time
        # (the batched backends call it from several worker threads).
        self.lock = threading.Lock()
        named = list(actor.named_parameters())
        self.names = [name for name, _ in named]
        self.shapes = [p.shape for _, p in named]
        self.sizes = [p.numel() for _, p in named]
        self.num_parameters = sum(self.sizes)

    def split(self, params: torch.Tensor) -> list[dict[str, torch.Tensor]]:
        """Per member, its parameters by name: views of its row, in ``actor.parameters()`` order
        (the layout of :func:`flat_parameters`)."""
        return [
            {name: piece.view(shape) for name, piece, shape in zip(self.names, row.split(self.sizes), self.shapes)}
            for row in params.detach()
        ]

    @torch.no_grad()
    def __call__(self, params: torch.Tensor, observations: torch.Tensor, layers=None) -> torch.Tensor:
        """Actions [P, act]; on one torch thread, as the batched forward runs (one observation per
        call: threads would only wait on each other, and on the simulator's)."""
        layers = self.split(params) if layers is None else layers
        with self.lock, torch_threads(1):
            return self._forward(layers, observations)

    def __getstate__(self) -> dict:  # picklable for Ray workers: a lock of their own
        return {k: v for k, v in self.__dict__.items() if k != "lock"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state, lock=threading.Lock())

    def _forward(self, layers, observations: torch.Tensor) -> torch.Tensor:
        actions = [
            functional_call(self.actor, member, (TensorDict(observation=observations[p : p + 1], batch_size=[1]),)).get("action")
            for p, member in enumerate(layers)
        ]
        return torch.cat(actions)


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
    """``actor`` as an :class:`ActorDescription` when it is ``TensorDictModule(MLP, observation)``
    then ``TanhModule -> action`` with an MLP :func:`describe_mlp` reads; else the reason."""
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
    return ActorDescription(mlp, steps[1])


class PopulationActor:
    """Evaluates P actors of one architecture at once from their stacked flat parameters
    (the fast counterpart of :class:`ModulePopulation`).

    ``actions = population_actor(params[P, D], observations[P, obs_dim])`` computes, for every
    member p, what ``make_actor`` would compute with ``load_flat_parameters(params[p])`` (equal
    up to float32 rounding), as one ``numpy.einsum("poi,pi->po")`` per layer over views of the
    flat vectors. Written by hand because no library call fits this shape well: each member
    multiplies its own weight matrix by one observation, so a generation is P matrix-vector
    products that read all P x D parameters per step (``python -m benchmarks.es_population``
    times it beside the alternatives). Every member's
    arithmetic is its own, so the forward over any contiguous block of members gives them
    bit for bit the actions of the forward over all P (``tests/test_networks.py``).
    """

    mirrored_pairs = True  # :meth:`mirrored` evaluates OpenAI-ES's pairs

    @staticmethod
    def refusal(actor) -> str | None:
        """None where this forward computes what ``actor`` computes (a :func:`make_actor` MLP:
        biased Linear layers with tanh or ReLU between them, squashed by a non-clamping
        ``TanhModule``), else why not (:func:`describe_actor`)."""
        description = describe_actor(actor)
        if isinstance(description, str):
            return description
        if description.tanh_module.clamp:
            return "TanhModule clamps"
        reason = description.mlp.plain_refusal()
        return None if reason is None else f"actor MLP: {reason}"

    @staticmethod
    def supports(actor) -> bool:
        return PopulationActor.refusal(actor) is None

    def __init__(self, actor: TensorDictSequential):
        reason = self.refusal(actor)
        if reason is not None:
            raise ValueError(f"PopulationActor computes biased Linear layers with tanh or ReLU between them only; this actor differs ({reason}: {_describe(actor)}): use ModulePopulation")
        description = describe_actor(actor)
        tanh_module = description.tanh_module
        self.layers: list[tuple[int, int]] = description.mlp.sizes  # (out_features, in_features) per Linear
        self.activations = [_NUMPY_ACTIVATIONS[layer.activation] for layer in description.mlp.layers[:-1]]  # after each hidden Linear
        self.low = tanh_module.action_low.detach().numpy().astype(np.float32)
        self.high = tanh_module.action_high.detach().numpy().astype(np.float32)
        self.non_trivial = bool(tanh_module.non_trivial)
        self.num_parameters = sum(o * i + o for o, i in self.layers)

    def split(self, params: torch.Tensor) -> list[tuple[np.ndarray, np.ndarray]]:
        """Views of the stacked flat vectors as (weight [P, out, in], bias [P, out]) per layer."""
        flat = params.detach().numpy()
        population = flat.shape[0]
        views, offset = [], 0
        for out_f, in_f in self.layers:
            weight = flat[:, offset : offset + out_f * in_f].reshape(population, out_f, in_f)
            offset += out_f * in_f
            views.append((weight, flat[:, offset : offset + out_f]))
            offset += out_f
        return views

    def split_pairs(self, mirrored: Mirrored, pairs: slice = slice(None)) -> tuple[list, list]:
        """:meth:`split` of the center (as one row) and of the offsets of ``pairs``: the layer
        views :meth:`mirrored` takes."""
        return self.split(mirrored.center.reshape(1, -1)), self.split(mirrored.offsets[pairs])

    def __call__(self, params: torch.Tensor, observations: torch.Tensor, layers=None) -> torch.Tensor:
        layers = self.split(params) if layers is None else layers
        x = observations.detach().numpy()
        last = len(layers) - 1
        for i, (weight, bias) in enumerate(layers):
            x = np.einsum("poi,pi->po", weight, x) + bias
            if i < last:
                x = self.activations[i](x)
        return torch.from_numpy(self._squash(x))

    def mirrored(self, center_layers, offset_layers, observations: np.ndarray) -> np.ndarray:
        """Actions [2, K, act] of mirrored pairs on their observations [2, K, obs]: row ``[0, k]``
        is member ``center + offsets[k]``, row ``[1, k]`` member ``center - offsets[k]``.

        ``center_layers, offset_layers`` are :meth:`split_pairs` of the K pairs. ``(c +- s_k) x = c x +- s_k x``: per pair, one ``[out, in] x [in, 2]`` product with
        the center (which stays in cache) and one with the pair's offsets, which are read once for
        both members, half of what :meth:`__call__` reads. Every pair gets products of the same
        shapes, so a block of pairs gets bit for bit the actions of all K (one product over all
        2K observations would not: BLAS picks its kernel by size). The same actions up to float32 rounding, not bit for
        bit: the sums are split differently (tests/test_networks.py). Its matrix products go to
        numpy's BLAS: callers run it under :func:`one_blas_thread`.
        """
        x = observations
        last = len(center_layers) - 1
        for i, ((center_weight, center_bias), (offset_weight, offset_bias)) in enumerate(zip(center_layers, offset_layers)):
            pair_inputs = x.transpose(1, 2, 0)  # [K, in, 2]: each pair's two observations as columns
            shared = np.matmul(center_weight[0], pair_inputs)  # [K, out, 2]
            own = np.matmul(offset_weight, pair_inputs)
            y = np.empty((2, x.shape[1], center_weight.shape[1]), dtype=np.float32)
            np.add(shared[..., 0] + center_bias[0], own[..., 0] + offset_bias, out=y[0])
            np.subtract(shared[..., 1] + center_bias[0], own[..., 1] + offset_bias, out=y[1])
            x = self.activations[i](y) if i < last else y
        return self._squash(x)

    def _squash(self, x: np.ndarray) -> np.ndarray:
        """``TanhModule``'s squashing of the last layer's output into the action bounds."""
        x = np.tanh(x)
        if self.non_trivial:
            x = self.low + (self.high - self.low) * (x + 1) / 2
        return x


_BLAS: list[ThreadpoolController] = []  # built on first use: it inspects the loaded libraries


def one_blas_thread():
    """Context manager: numpy's BLAS (OpenBLAS) on one thread inside the block, as
    :meth:`PopulationActor.mirrored` is measured and meant to run during a rollout (BLAS threads
    of their own would compete with MuJoCo's for the cores)."""
    if not _BLAS:
        _BLAS.append(ThreadpoolController().select(internal_api="openblas"))
    return _BLAS[0].limit(limits=1)


def _describe(actor) -> str:
    """The actor's modules in one line, for the refusal messages of the hand-written forwards."""
    return " ".join(str(actor).split())[:200]


def _relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, 0, dtype=x.dtype)


_NUMPY_ACTIVATIONS = {"tanh": np.tanh, "relu": _relu}  # PopulationActor's kernels of FAST_ACTIVATIONS


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


def es_population(actor, pieces) -> type:
    """The class that computes ES members' actions: :class:`PopulationActor` where the ``es_forward``
    piece is chosen and it computes exactly what ``actor`` does (tanh/ReLU MLPs), else the reference
    :class:`ModulePopulation` (:mod:`torchrl_esrl.run.implementation`)."""
    return PopulationActor if "es_forward" in pieces and PopulationActor.supports(actor) else ModulePopulation


def actor_parameters(cfg, sizes) -> int:
    """The number of parameters of :func:`make_actor_critic`'s actor for a task of ``sizes`` (:class:`~torchrl_esrl.envs.EnvSizes`)."""
    return mlp_parameters([sizes.observation_dim, *cfg.actor.hidden, sizes.action_dim])
