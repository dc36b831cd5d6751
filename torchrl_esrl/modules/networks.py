"""Actor and critic networks of ES-TD3Buffers (paper, Section 4.2 "Architecture").

The actor is shared by both halves of the algorithm: TD3 trains it by gradient
descent, OpenAI-ES searches over its *flat parameter vector*. `flat_parameters`
and `load_flat_parameters` are the bridge between the two views, and
`PopulationActor` evaluates many flat vectors at once (one batched forward for
a whole ES population).
"""
from __future__ import annotations

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
    member p, exactly what ``make_actor`` would compute with ``load_flat_parameters(params[p])``,
    using one ``torch.baddbmm`` per layer instead of P module calls. Written by hand because
    ``torch.func.vmap(functional_call)`` measured 2x slower for this shape (see
    ``shared/notes/stack-facts.md``).
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
        self.act = torch.tanh if self.activation is nn.Tanh else torch.relu
        self.low = tanh_module.action_low.detach().clone()
        self.high = tanh_module.action_high.detach().clone()
        self.non_trivial = bool(tanh_module.non_trivial)
        self.num_parameters = sum(o * i + o for o, i in self.layers)

    def split(self, params: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Views of the stacked flat vectors as (weight^T [P, in, out], bias [P, 1, out]) per layer."""
        population = params.shape[0]
        views, offset = [], 0
        for out_f, in_f in self.layers:
            weight = params[:, offset : offset + out_f * in_f].view(population, out_f, in_f)
            offset += out_f * in_f
            bias = params[:, offset : offset + out_f].view(population, 1, out_f)
            offset += out_f
            views.append((weight.transpose(1, 2), bias))
        return views

    @torch.no_grad()
    def __call__(self, params: torch.Tensor, observations: torch.Tensor, layers=None) -> torch.Tensor:
        layers = self.split(params) if layers is None else layers
        x = observations.unsqueeze(1)  # [P, 1, obs]
        last = len(layers) - 1
        for i, (weight_t, bias) in enumerate(layers):
            x = torch.baddbmm(bias, x, weight_t)
            if i < last:
                x = self.act(x)
        x = x.squeeze(1).tanh()
        if self.non_trivial:
            x = self.low + (self.high - self.low) * (x + 1) / 2
        return x
