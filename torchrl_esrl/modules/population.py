"""The evaluation of ES populations: many flat parameter vectors of one actor at once, each member
acting as the actor would with its vector loaded (paper, Section 3: ES searches over the actor's
flat parameters).

Two classes evaluate them: `ModulePopulation` (the reference: the actor module itself, through
``torch.func.functional_call``) and `PopulationActor` (one batched numpy forward for a whole ES
population, for the plain MLP actors of `make_actor`, decided from
:func:`~torchrl_esrl.modules.networks.describe_actor` and the probes beside it). `Mirrored` tells
them OpenAI-ES's mirrored pairs; `es_population` picks the class a run evaluates with.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from threadpoolctl import ThreadpoolController
from torch import nn
from torch.func import functional_call
from torch.nn.utils import parameters_to_vector

from torchrl_esrl.modules.networks import describe_actor, forward_difference, nondeterminism, probe_observations
from torchrl_esrl.threads import torch_threads


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

    def nondeterminism(self, observation_dim: int) -> str | None:
        """Why its members' actions are not a deterministic function of their parameters and
        observation (the actor's forward draws random numbers, or keeps state: :func:`nondeterminism`),
        or None. Backends that play members in an order that varies from run to run need None."""
        reason = nondeterminism(self.actor, observation_dim)
        return None if reason is None else f"actor: {reason}"

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
    bit for bit the actions of the forward over all P (``tests/test_population.py``).
    """

    mirrored_pairs = True  # :meth:`mirrored` evaluates OpenAI-ES's pairs

    @staticmethod
    def refusal(actor) -> str | None:
        """None where this forward computes what ``actor`` computes, else why not: decided from
        its description (:func:`describe_actor`: a :func:`make_actor` MLP of biased Linear layers
        with tanh or ReLU between them, squashed by a non-clamping ``TanhModule``, nothing run
        around its modules' forwards), then by comparison (:meth:`difference`: this forward
        against the actor module's own on a few observations)."""
        reason = PopulationActor._description_refusal(actor)
        if reason is not None:
            return reason
        population = object.__new__(PopulationActor)
        population._build(actor)
        return population.difference(actor)

    @staticmethod
    def supports(actor) -> bool:
        return PopulationActor.refusal(actor) is None

    def __init__(self, actor: TensorDictSequential):
        reason = self._description_refusal(actor)
        if reason is None:
            self._build(actor)
            reason = self.difference(actor)
        if reason is not None:
            raise ValueError(f"PopulationActor computes biased Linear layers with tanh or ReLU between them only; this actor differs ({reason}: {_describe(actor)}): use ModulePopulation")

    @staticmethod
    def _description_refusal(actor) -> str | None:
        description = describe_actor(actor)
        if isinstance(description, str):
            return description
        if description.tanh_module.clamp:
            return "TanhModule clamps"
        reason = description.mlp.plain_refusal()
        return None if reason is None else f"actor MLP: {reason}"

    def _build(self, actor) -> None:
        description = describe_actor(actor)
        tanh_module = description.tanh_module
        self.layers: list[tuple[int, int]] = description.mlp.sizes  # (out_features, in_features) per Linear
        self.activations = [_NUMPY_ACTIVATIONS[layer.activation] for layer in description.mlp.layers[:-1]]  # after each hidden Linear
        self.low = tanh_module.action_low.detach().numpy().astype(np.float32)
        self.high = tanh_module.action_high.detach().numpy().astype(np.float32)
        self.non_trivial = bool(tanh_module.non_trivial)
        self.num_parameters = sum(o * i + o for o, i in self.layers)

    def difference(self, actor) -> str | None:
        """Why this forward does not give ``actor``'s actions on :func:`probe_observations`, each
        member the actor's own parameters, through :meth:`__call__` and :meth:`mirrored`
        (:func:`forward_difference`), or None."""
        observations = probe_observations(self.layers[0][1])
        center = parameters_to_vector(actor.parameters()).detach().float()
        members = center.expand(len(observations), -1)  # every member the actor itself
        mirrored = Mirrored(center, torch.zeros(1, center.numel()).expand(len(observations) // 2, -1))

        def pairs(x: torch.Tensor) -> torch.Tensor:
            return torch.from_numpy(self.mirrored(*self.split_pairs(mirrored), x.numpy().reshape(2, len(x) // 2, -1)).reshape(len(x), -1))

        span = torch.from_numpy(self.high - self.low) if self.non_trivial else torch.tensor(2.0)
        return forward_difference(actor, {"the batched forward": lambda x: self(members, x), "the mirrored forward": pairs}, observations, span)

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
        bit: the sums are split differently (tests/test_population.py). Its matrix products go to
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


_NUMPY_ACTIVATIONS = {"tanh": np.tanh, "relu": _relu}  # PopulationActor's kernels of networks.FAST_ACTIVATIONS


def es_population(actor, pieces) -> type:
    """The class that computes ES members' actions: :class:`PopulationActor` where the ``es_forward``
    piece is chosen and it computes what ``actor`` does (tanh/ReLU MLPs, nothing run around their
    modules, the same actions on the probe's observations: :meth:`PopulationActor.refusal`), else the
    reference :class:`ModulePopulation` (:mod:`torchrl_esrl.run.implementation`)."""
    return PopulationActor if "es_forward" in pieces and PopulationActor.supports(actor) else ModulePopulation
