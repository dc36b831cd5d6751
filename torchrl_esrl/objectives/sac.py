"""SAC in the TD3 phase's place (``learner=sac``): soft actor-critic with automatic entropy tuning
(Haarnoja et al. 2018, "Soft Actor-Critic Algorithms and Applications": twin critics and their
targets, no value network, Adam 3e-4 for actor, critics and temperature, tau 0.005, target
entropy -dim(A)), over TorchRL's ``SACLoss``, ``SoftUpdate`` and ``torch.optim.Adam``.

The policy is a tanh-squashed Gaussian (TorchRL's ``ProbabilisticActor`` over ``TanhNormal``)
whose mean path is :func:`~torchrl_esrl.modules.networks.make_actor`'s actor itself: the same
MLP gives the Gaussian's location, a second linear head on its last hidden layer gives the scale.
:attr:`SAC.actor` is that deterministic actor (tanh of the location, mapped to the action
bounds: the policy's deterministic mode): what evaluations play and what ES perturbs and
overwrites; the scale head is the SAC policy's own (docs/deviations.md).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from tensordict import TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType
from torchrl.modules import ProbabilisticActor, TanhNormal
from torchrl.objectives import SACLoss

from torchrl_esrl.modules.networks import make_actor
from torchrl_esrl.objectives.learner import StockLearner
from torchrl_esrl.run.capacity import mlp_parameters
from torchrl_esrl.run.schema import number, one_of, positive


@dataclass
class SACConfig:
    """The ``sac`` section (``learner=sac``): Haarnoja et al. (2018b), Table 1."""

    actor_lr: float = positive(3.0e-4)
    critic_lr: float = positive(3.0e-4)
    alpha_lr: float = positive(3.0e-4)  # the entropy temperature's Adam
    gamma: float = number(0.99, low=0, high=1)
    tau: float = number(0.005, low=0, high=1, low_open=True)
    alpha_init: float = positive(1.0)  # initial entropy temperature
    fixed_alpha: bool = False  # true: the temperature stays alpha_init (SAC without automatic tuning)
    target_entropy: Optional[float] = number(None)  # null: -dim(A), Haarnoja et al.'s heuristic
    loss_function: str = one_of("l2", ("l2", "l1", "smooth_l1"))  # critic regression loss (torchrl.objectives.utils.distance_loss)


class GaussianHeads(nn.Module):
    """``observation -> (loc, scale)``: the location is ``mlp``'s output, the scale a linear head on
    ``mlp``'s last hidden features, through TorchRL's ``NormalParamExtractor`` (biased softplus)."""

    def __init__(self, mlp: nn.Sequential, action_dim: int):
        super().__init__()
        layers = list(mlp.children())
        self.features = nn.Sequential(*layers[:-1])  # the same modules as `mlp`'s: shared parameters
        self.loc = layers[-1]
        self.scale = nn.Linear(self.loc.in_features, action_dim)
        self.extract = NormalParamExtractor()

    def forward(self, observation: torch.Tensor):
        features = self.features(observation)
        return self.extract(torch.cat([self.loc(features), self.scale(features)], -1))


def make_sac_actor(observation_dim: int, action_spec, hidden=(256, 256), activation: str = "tanh") -> tuple:
    """``(policy, actor)``: the SAC policy (``ProbabilisticActor``, tanh-normal in the action bounds,
    sampling when it acts) and its deterministic mean path, :func:`make_actor`'s actor, whose
    parameters the policy shares."""
    actor = make_actor(observation_dim, action_spec, hidden, activation)
    heads = GaussianHeads(actor.module[0].module, action_spec.shape[-1])
    policy = ProbabilisticActor(
        TensorDictModule(heads, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        spec=action_spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": action_spec.space.low, "high": action_spec.space.high, "tanh_loc": False},
        default_interaction_type=ExplorationType.RANDOM,
    )
    return policy, actor


class SAC(StockLearner):
    """SAC as TorchRL's ``sota-implementations/sac`` updates it: per step one ``SACLoss`` forward,
    the critic, actor and temperature losses backpropagated together (each reaches only its own
    parameters), one Adam step each, then the soft update of the target critics.

    Args:
        policy, actor: :func:`make_sac_actor`'s.
        critic: Q network template; ``SACLoss`` makes the twin critics from it.
        action_spec: the action bounds (the target entropy's dimension).
        num_threads: torch threads of the phase (None: leave the process's count).
    """

    name = "sac"
    # Parameter vectors held, for the run's memory estimate: the policy (mean and scale heads) and
    # Adam's two moments, plus the exploration policy's copy in the checkpoint; each of the twin
    # critics, its target and two moments.
    HELD_ACTOR_COPIES = 3 + 1
    HELD_CRITIC_COPIES = 2 * 4

    def __init__(self, policy, actor, critic, action_spec, actor_lr=3e-4, critic_lr=3e-4, alpha_lr=3e-4, gamma=0.99, tau=0.005,
                 alpha_init=1.0, fixed_alpha=False, target_entropy=None, loss_function="l2", num_threads=None):
        loss = SACLoss(
            policy, critic, num_qvalue_nets=2, loss_function=loss_function, alpha_init=alpha_init, fixed_alpha=fixed_alpha,
            action_spec=action_spec, target_entropy="auto" if target_entropy is None else target_entropy, delay_qvalue=True,
        )
        loss.make_value_estimator(gamma=gamma)
        loss.target_entropy  # noqa: B018 - made on first use: made now, so that every state_dict has it
        optimizers = {
            "critic": torch.optim.Adam(list(loss.qvalue_network_params.values(True, True)), lr=critic_lr),
            "actor": torch.optim.Adam(list(policy.parameters()), lr=actor_lr),  # the loss shares storage with `policy`
        }
        if not fixed_alpha:
            optimizers["alpha"] = torch.optim.Adam([loss.log_alpha], lr=alpha_lr)
        super().__init__(actor, policy, loss, optimizers, tau, num_threads)

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        out = self.loss(batch)
        losses = {"critic": out["loss_qvalue"], "actor": out["loss_actor"], "alpha": out["loss_alpha"]}
        for optimizer in self.optimizers.values():
            optimizer.zero_grad(set_to_none=True)
        sum(losses.values()).backward()
        values = {f"{name}_loss": self.checked(name, loss) for name, loss in losses.items()}
        for optimizer in self.optimizers.values():
            optimizer.step()
        self.target_update.step()
        self.updates += 1
        return values

    def metrics(self) -> dict[str, float]:
        """The entropy temperature alpha, now."""
        return {"alpha": float(self.loss.log_alpha.detach().exp())}

    @staticmethod
    def policy_parameters(hidden, sizes) -> int:
        """Parameters of the policy, mean path and scale head (the memory estimate's unit,
        :func:`~torchrl_esrl.objectives.learners.learner_holdings`)."""
        return mlp_parameters([sizes.observation_dim, *hidden, sizes.action_dim]) + mlp_parameters([hidden[-1], sizes.action_dim])
