"""DDPG in the TD3 phase's place (``learner=ddpg``): Fujimoto et al.'s (2018) re-tuned DDPG
("OurDDPG" of their code: 2x256 networks, Adam 3e-4 for both, tau 0.005, batch 256, Gaussian
exploration noise 0.1), over TorchRL's ``DDPGLoss``, ``SoftUpdate`` and ``torch.optim.Adam``.

It differs from TD3 by what TD3 added to it: one critic, no target policy smoothing, the actor and
the targets updated at every step (docs/deviations.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torchrl.objectives import DDPGLoss

from torchrl_esrl.objectives.learner import StockLearner, gaussian_exploration
from torchrl_esrl.run.capacity import mlp_parameters
from torchrl_esrl.run.schema import number, one_of, positive


@dataclass
class DDPGConfig:
    """The ``ddpg`` section (``learner=ddpg``): OurDDPG's values (Fujimoto et al. 2018)."""

    actor_lr: float = positive(3.0e-4)
    critic_lr: float = positive(3.0e-4)
    gamma: float = number(0.99, low=0, high=1)
    tau: float = number(0.005, low=0, high=1, low_open=True)
    exploration_noise: float = number(0.1, low=0)  # std of the Gaussian noise added to actions when acting
    loss_function: str = one_of("l2", ("l2", "l1", "smooth_l1"))  # critic regression loss (torchrl.objectives.utils.distance_loss)


class DDPG(StockLearner):
    """DDPG (Lillicrap et al. 2016) as Fujimoto et al.'s OurDDPG trains it: per step a critic Adam
    step on ``DDPGLoss.loss_value``, then an actor Adam step on ``loss_actor`` (the updated critic,
    detached), then the soft update of both targets.

    Args:
        actor: deterministic actor (``observation -> action``), the ES vector's network.
        critic: Q network (``observation, action -> state_action_value``).
        action_spec: bounds of the exploration noise.
        num_threads: torch threads of the phase (None: leave the process's count).
    """

    name = "ddpg"
    # Parameter vectors held, for the run's memory estimate: the actor, its target and Adam's two
    # moments, plus the exploration policy's copy in the checkpoint; the critic, its target, two moments.
    HELD_ACTOR_COPIES = 4 + 1
    HELD_CRITIC_COPIES = 4

    def __init__(self, actor, critic, action_spec, actor_lr=3e-4, critic_lr=3e-4, gamma=0.99, tau=0.005, exploration_noise=0.1, loss_function="l2", num_threads=None):
        loss = DDPGLoss(actor, critic, loss_function=loss_function, delay_actor=True, delay_value=True)
        loss.make_value_estimator(gamma=gamma)
        optimizers = {
            "critic": torch.optim.Adam(list(loss.value_network_params.values(True, True)), lr=critic_lr),
            "actor": torch.optim.Adam(list(actor.parameters()), lr=actor_lr),  # the loss shares storage with `actor`
        }
        super().__init__(actor, gaussian_exploration(actor, action_spec, exploration_noise), loss, optimizers, tau, num_threads)

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        out = {"critic_loss": self.gradient_step("critic", self.loss.loss_value(batch)[0])}
        out["actor_loss"] = self.gradient_step("actor", self.loss.loss_actor(batch)[0])
        self.target_update.step()
        self.updates += 1
        return out

    @staticmethod
    def policy_parameters(hidden, sizes) -> int:
        """Parameters of the actor (the memory estimate's unit, :func:`~torchrl_esrl.objectives.learners.learner_holdings`)."""
        return mlp_parameters([sizes.observation_dim, *hidden, sizes.action_dim])
