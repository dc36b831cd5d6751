"""Actor and critic networks of ES-TD3Buffers (paper, Section 4.2 "Architecture").

The actor is shared by both halves of the algorithm: TD3 trains it by gradient
descent, OpenAI-ES searches over its *flat parameter vector*. `flat_parameters`
and `load_flat_parameters` are the bridge between the two views, and
`PopulationActor` evaluates many flat vectors at once (one batched forward for
a whole ES population).
"""
from __future__ import annotations

import numpy as np
import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torch.nn.utils import parameters_to_vector, vector_to_parameters
from torchrl.data import TensorSpec
from torchrl.modules import MLP, TanhModule, ValueOperator

ACTIVATIONS = {"tanh": nn.Tanh, "relu": nn.ReLU}


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
    """Copy ``vector`` into the actor's parameters, in place (optimiser references stay valid)."""
    reference = next(actor.parameters())
    vector_to_parameters(vector.to(device=reference.device, dtype=reference.dtype), actor.parameters())


class PopulationActor:
    """Evaluates P actors of one architecture at once from their stacked flat parameters.

    ``actions = population_actor(params[P, D], observations[P, obs_dim])`` computes, for every
    member p, what ``make_actor`` would compute with ``load_flat_parameters(params[p])`` (equal
    up to float32 rounding), as one ``numpy.einsum("poi,pi->po")`` per layer over views of the
    flat vectors. Written by hand because no library call fits this shape well: each member
    multiplies its own weight matrix by one observation, so a generation is P matrix-vector
    products that read all P x D parameters per step. Measured on the 2-core machine (120
    members, HalfCheetah sizes, one thread): this einsum 2.4 ms, ``torch.baddbmm`` per layer
    5.5 ms, ``numpy.matmul`` 3.7 ms, ``vmap(functional_call)`` and a loop over modules slower
    still (``benchmarks/es_population.py``; ``shared/notes/stack-facts.md``). Every member's
    arithmetic is its own, so the forward over any contiguous block of members gives them
    bit for bit the actions of the forward over all P (``tests/test_networks.py``).
    """

    def __init__(self, actor: TensorDictSequential):
        mlp = actor[0].module
        tanh_module = actor[1]
        self.layers: list[tuple[int, int]] = []  # (out_features, in_features) per Linear
        self.activation: type[nn.Module] | None = None
        for module in mlp:
            if isinstance(module, nn.Linear):
                self.layers.append((module.out_features, module.in_features))
            elif self.activation is None:
                self.activation = type(module)
        self.act = np.tanh if self.activation is nn.Tanh else _relu
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

    def __call__(self, params: torch.Tensor, observations: torch.Tensor, layers=None) -> torch.Tensor:
        layers = self.split(params) if layers is None else layers
        x = observations.detach().numpy()
        last = len(layers) - 1
        for i, (weight, bias) in enumerate(layers):
            x = np.einsum("poi,pi->po", weight, x) + bias
            if i < last:
                x = self.act(x)
        x = np.tanh(x)
        if self.non_trivial:
            x = self.low + (self.high - self.low) * (x + 1) / 2
        return torch.from_numpy(x)


def _relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, 0, dtype=x.dtype)
