"""The learner of Algorithm 1's TD3 phase, as the run plumbing sees it.

The paper's learner is TD3 (:class:`~torchrl_esrl.objectives.td3.TD3`); ``learner=ddpg`` and
``learner=sac`` put :class:`~torchrl_esrl.objectives.ddpg.DDPG` or
:class:`~torchrl_esrl.objectives.sac.SAC` in its place (:mod:`torchrl_esrl.objectives.learners`
builds the one the config names). The run finds a recipe's learner by the members of
:class:`Learner`, never by its class: the checkpoint saves its ``state_dict``, ``summary.json``'s
``threads`` names its ``num_threads``, and the pieces line says which fast pieces it runs
(:meth:`Learner.pieces`).
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.modules import AdditiveGaussianModule
from torchrl.objectives import LossModule, SoftUpdate

from torchrl_esrl.errors import check_finite


@runtime_checkable
class Learner(Protocol):
    """What a learner of the TD3 phase has.

    ``actor``: the deterministic policy (``observation -> action``): what the learner's evaluations
    play, and the parameters ES perturbs and overwrites (``flat_parameters(actor)``).
    ``exploration_policy``: what acts in the env while the phase collects (noise or sampling).
    ``num_threads``: torch threads of the phase (None: leave the process's count).
    ``updates``: gradient updates taken so far.
    """

    actor: nn.Module
    exploration_policy: TensorDictModuleBase
    num_threads: int | None
    updates: int

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """One update on a sampled batch; its losses by name (``critic_loss``, ``actor_loss``...)."""

    def pieces(self) -> dict[str, tuple[bool, str | None]]:
        """Each fast piece of its update (``td3_loss``, ``soft_update``, ``adam``: TD3's, of
        :data:`~torchrl_esrl.run.implementation.FAST_PIECES`): whether it runs, and why not where the
        reference runs in its place (None: no reason to give)."""

    def metrics(self) -> dict[str, float]:
        """Values of the learner's own state worth a column of ``metrics.csv`` (SAC's entropy
        coefficient); TD3 and DDPG have none."""

    def state_dict(self) -> dict:
        """Everything an exact resume needs: networks, targets, optimisers, counters."""

    def load_state_dict(self, state: dict) -> None: ...


def gaussian_exploration(actor, action_spec, std: float) -> TensorDictSequential:
    """``actor`` followed by TorchRL's ``AdditiveGaussianModule`` of constant ``std``: TD3's and
    DDPG's behaviour policy (Fujimoto et al. 2018), which the fast TD3 collector steps exactly. Its
    buffers are on the actor's device: TorchRL's ``Collector`` steps a policy wholly on its device
    itself, and a copy of any other."""
    device = next(actor.parameters()).device
    return TensorDictSequential(actor, AdditiveGaussianModule(spec=action_spec, sigma_init=1.0, sigma_end=1.0, mean=0.0, std=float(std), device=device))


class StockLearner:
    """What DDPG and SAC share: a TorchRL loss module, TorchRL's ``SoftUpdate`` of its targets and
    one ``torch.optim.Adam`` per parameter group, all stock (the fast pieces are TD3's).

    Subclasses build ``loss`` and ``optimizers`` (name -> Adam) and write :meth:`update`.
    """

    name = ""  # the learner= value

    def __init__(self, actor, exploration_policy, loss: LossModule, optimizers: dict[str, torch.optim.Adam], tau: float, num_threads: int | None):
        self.actor = actor
        self.exploration_policy = exploration_policy
        self.loss = loss
        self.optimizers = optimizers
        self.target_update = SoftUpdate(loss, tau=tau)
        self.num_threads = num_threads
        self.updates = 0

    def checked(self, name: str, loss: torch.Tensor) -> float:
        """``loss`` as a float; FloatingPointError naming it where it is not finite (before any step)."""
        return check_finite(f"{self.name.upper()} {name} loss at update {self.updates}", loss.item())

    def gradient_step(self, name: str, loss: torch.Tensor) -> float:
        """``zero_grad``, ``backward``, ``step`` of the ``name`` optimiser on ``loss``; returns it."""
        optimizer = self.optimizers[name]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        value = self.checked(name, loss)
        optimizer.step()
        return value

    def pieces(self) -> dict[str, tuple[bool, str | None]]:
        loss = type(self.loss).__name__
        return {
            "td3_loss": (False, f"learner={self.name}: the hand-written gradients are TD3Loss's; {loss} with autograd runs"),
            "soft_update": (False, f"learner={self.name}: proven equal on TD3's targets only; SoftUpdate runs"),
            "adam": (False, f"learner={self.name}: proven equal on TD3's update only; torch.optim.Adam runs"),
        }

    def metrics(self) -> dict[str, float]:
        return {}

    def state_dict(self) -> dict:
        return {
            "loss": self.loss.state_dict(),
            **{f"{name}_optimizer": optimizer.state_dict() for name, optimizer in self.optimizers.items()},
            "updates": self.updates,
        }

    def load_state_dict(self, state: dict) -> None:
        self.loss.load_state_dict(state["loss"])
        for name, optimizer in self.optimizers.items():
            optimizer.load_state_dict(state[f"{name}_optimizer"])
        self.updates = int(state["updates"])
