"""TD3 half of ES-TD3Buffers (paper, Algorithm 1 "perform TD3 iterations"; Fujimoto et al. 2018).

:class:`TD3` holds TorchRL's :class:`~torchrl.objectives.TD3Loss` (twin critics, target policy
smoothing), the :class:`~torchrl.objectives.SoftUpdate` of the targets, one Adam per network and
the policy delay; :func:`torchrl_esrl.algorithm.td3_phase.td3_phase` runs it inside Algorithm 1.
"""
from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Collection

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictSequential
from torchrl.objectives import SoftUpdate, TD3Loss

from torchrl_esrl.errors import check_finite
from torchrl_esrl.modules.networks import NETWORK_FIELD, actor_parameters
from torchrl_esrl.modules.warmup import RandomWarmup
from torchrl_esrl.objectives.learner import gaussian_exploration
from torchrl_esrl.objectives.manual_grad import ManualGradTD3Loss, TD3LossQ1Actor, backward
from torchrl_esrl.run.capacity import Holding, mlp_parameters, network_holding
from torchrl_esrl.run.implementation import chosen_pieces
from torchrl_esrl.threads import job_cores
from torchrl_esrl.torchrl_private import foreach_lerp_, fused_adam_step, soft_update_tensors

run_record = logging.getLogger("torchrl_esrl.run")  # the run directory's <recipe>.log (conf/hydra/job_logging/run_log.yaml)

__all__ = ["TD3", "ForeachSoftUpdate", "ManualGradTD3Loss", "TD3LossQ1Actor"]

class ForeachSoftUpdate(SoftUpdate):
    """``SoftUpdate`` with one foreach ``lerp_`` over all target tensors.

    ``SoftUpdate.step`` looks the targets up through the loss module and calls ``lerp_`` once per
    tensor; the arithmetic is the same ``target.lerp_(source, tau)``, so results are identical
    (tests/test_td3.py). The source/target tensor lists are built once: TorchRL keeps the
    parameters in place for the life of the loss.
    """

    def step(self) -> None:
        if not self.initialized:
            raise RuntimeError("ForeachSoftUpdate must be initialized (init_()) before step()")
        pairs = self.__dict__.get("_pairs")
        if pairs is None:
            pairs = self.__dict__["_pairs"] = soft_update_tensors(self)
        foreach_lerp_(pairs[1], pairs[0], 1 - self.eps)


def zero_grads(optimizer: torch.optim.Optimizer) -> None:
    """``optimizer.zero_grad(set_to_none=True)``: every parameter's ``.grad`` set to None. torch's
    ``Optimizer.zero_grad`` does this inside a ``record_function`` profiler range, which costs several
    times the loop over a few parameters; an optimizer class with its own ``zero_grad`` gets that one."""
    if type(optimizer).zero_grad is not torch.optim.Optimizer.zero_grad:
        optimizer.zero_grad(set_to_none=True)
        return
    for group in optimizer.param_groups:
        for parameter in group["params"]:
            parameter.grad = None


class TD3:
    """TD3 (Fujimoto et al. 2018) over an actor and a critic template (two critics are made from it),
    updated as TorchRL's ``sota-implementations/td3``: per step ``zero_grad``, ``value_loss``,
    ``backward``, ``step``; every ``policy_delay`` steps the same for ``actor_loss``, then the soft
    target update.

    Args:
        actor: deterministic actor (``observation -> action``).
        critic: Q network (``observation, action -> state_action_value``).
        action_spec: bounds used by the target policy smoothing and the exploration noise.
        lr: Adam learning rate of actor and critics (paper: 3e-4).
        gamma: discount.
        tau: soft target update rate (paper: 0.005).
        policy_noise, noise_clip: target policy smoothing of TD3.
        policy_delay: critic updates per actor/target update.
        exploration_noise: std of the Gaussian noise added to actions when acting (paper: 0.1).
        loss_function: critic regression loss (``"l2"`` as in Fujimoto's TD3).
        num_qvalue_nets: critics made from ``critic`` (TD3: 2).
        loss_class: the ``TD3Loss`` class (or a subclass) to build: stock ``TD3Loss`` (the
            reference) or :class:`ManualGradTD3Loss` (hand-written forwards and gradients where it
            computes exactly what ``TD3Loss`` would, ``TD3Loss``'s code elsewhere).
        target_update_class: ``SoftUpdate`` (the reference) or :class:`ForeachSoftUpdate`.
        optimizer_impl: ``"default"`` (torch's ``Adam`` as constructed by default, the
            reference), ``"foreach"``, or ``"fused"`` (fused Adam, stepped by one direct kernel
            call: :func:`~torchrl_esrl.torchrl_private.fused_adam_step`).
        num_threads: torch threads while :func:`~torchrl_esrl.algorithm.td3_phase.td3_phase` runs
            (None: leave the process's count; docs/performance.md).
        precision: ``"fp32"`` or ``"bf16"``: the losses computed under
            ``torch.autocast(dtype=torch.bfloat16)`` (matrix products and activations in bfloat16,
            loss values in float32; :meth:`ManualGradTD3Loss.matmul_dtype
            <torchrl_esrl.objectives.manual_grad.ManualGradTD3Loss.matmul_dtype>`), the backward
            outside it; parameters, gradients, Adam's moments and the targets stay float32.

    To change the gradients (an extra loss term, clipping), override :meth:`backward` in a
    subclass; hooks on the parameters or optimizers, and frozen parameters
    (``requires_grad_(False)``), work as in any PyTorch training loop, with every ``loss_class``.

    The reference is TorchRL's stock TD3 (``TD3Loss``, ``SoftUpdate``, ``Adam``);
    :func:`make_td3` builds it from the config with the fast pieces chosen. It is the paper's
    :class:`~torchrl_esrl.objectives.learner.Learner` (``learner=td3``, the default).
    """

    # Parameter vectors held (and checkpointed), for the run's memory estimate: the actor, its
    # target and Adam's two moments, plus the exploration policy's copy; each critic of the twin
    # pair, its target and Adam's two moments.
    HELD_ACTOR_COPIES = 4 + 1
    HELD_CRITIC_COPIES = 2 * 4
    PRECISIONS = ("fp32", "bf16")

    def __init__(
        self,
        actor: TensorDictSequential,
        critic,
        action_spec,
        lr: float = 3e-4,
        gamma: float = 0.99,
        tau: float = 0.005,
        policy_noise: float = 0.2,
        noise_clip: float = 0.5,
        policy_delay: int = 2,
        exploration_noise: float = 0.1,
        loss_function: str = "l2",
        num_qvalue_nets: int = 2,
        loss_class: type[TD3Loss] = TD3Loss,
        target_update_class: type[SoftUpdate] = SoftUpdate,
        optimizer_impl: str = "default",
        num_threads: int | None = None,
        precision: str = "fp32",
    ):
        self.actor = actor
        self.action_spec = action_spec
        self.loss = loss_class(
            actor_network=actor,
            qvalue_network=critic,
            action_spec=action_spec,
            num_qvalue_nets=num_qvalue_nets,
            policy_noise=policy_noise,
            noise_clip=noise_clip,
            loss_function=loss_function,
            delay_actor=True,
            delay_qvalue=True,
        )
        self.loss.make_value_estimator(gamma=gamma)
        self.target_update = target_update_class(self.loss, tau=tau)
        # The loss shares storage with `actor`; the critics live in the loss's stacked params.
        if optimizer_impl not in ("fused", "foreach", "default"):
            raise ValueError(f"optimizer_impl must be fused, foreach or default, got {optimizer_impl!r}")
        self.optimizer_impl = optimizer_impl
        options = {"fused": {"fused": True}, "foreach": {"foreach": True}, "default": {}}[optimizer_impl]
        self.actor_optimizer = torch.optim.Adam(list(actor.parameters()), lr=lr, **options)
        self.critic_optimizer = torch.optim.Adam(list(self.loss.qvalue_network_params.values(True, True)), lr=lr, **options)
        self.policy_delay = int(policy_delay)
        self.exploration_policy = gaussian_exploration(actor, action_spec, exploration_noise)
        self.num_threads = num_threads
        if precision not in self.PRECISIONS:
            raise ValueError(f"precision must be {' or '.join(self.PRECISIONS)}, got {precision!r}")
        self.precision = precision
        device_type = next(actor.parameters()).device.type
        self._loss_context = (lambda: torch.autocast(device_type, dtype=torch.bfloat16)) if precision == "bf16" else contextlib.nullcontext
        self.updates = 0

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """One TD3 step: critic update; every ``policy_delay`` steps actor and target updates."""
        out = {"critic_loss": self.gradient_step(self.loss.value_loss, batch, self.critic_optimizer, f"TD3 critic loss at update {self.updates}")}
        self.updates += 1
        if self.updates % self.policy_delay == 0:
            out["actor_loss"] = self.gradient_step(self.loss.actor_loss, batch, self.actor_optimizer, f"TD3 actor loss at update {self.updates}")
            self.target_update.step()
        return out

    def gradient_step(self, loss_fn, batch: TensorDictBase, optimizer: torch.optim.Adam, name: str) -> float:
        """One step of ``optimizer`` (critic or actor Adam) on ``loss_fn(batch)`` (``self.loss.value_loss``
        or ``actor_loss``): ``zero_grad``, the loss at the run's ``precision``, :meth:`backward`, the
        step. Returns the loss; raises ``FloatingPointError`` naming ``name`` where it is not finite,
        before the step. :meth:`update` takes its steps through it, and so do CEM-RL's gradient steps
        (:func:`torchrl_esrl.es.cem.cem_rl_gradient_steps`): a subclass's :meth:`backward` acts on both."""
        self._zero_grad(optimizer)
        with self._loss_context():
            loss, _ = loss_fn(batch)
        self.backward(loss, optimizer)
        value = check_finite(name, loss.item())
        self._step(optimizer)
        return value

    def backward(self, loss: torch.Tensor, optimizer: torch.optim.Optimizer) -> None:
        """``loss.backward()`` before ``optimizer`` (critic or actor Adam) steps: the place for a
        subclass to add a loss term (``super().backward(loss + extra, optimizer)``) or to edit the
        gradients after it (``torch.nn.utils.clip_grad_norm_(optimizer.param_groups[0]["params"], c)``).
        The hand-written losses' gradients go into ``.grad`` as ``loss.backward()`` puts them
        (:func:`~torchrl_esrl.objectives.manual_grad.backward`)."""
        backward(loss)

    def _zero_grad(self, optimizer: torch.optim.Adam) -> None:
        """``optimizer.zero_grad(set_to_none=True)``; with fused Adam, the same without the profiler
        range torch opens around it (:func:`zero_grads`)."""
        zero_grads(optimizer) if self.optimizer_impl == "fused" else optimizer.zero_grad(set_to_none=True)

    def _step(self, optimizer: torch.optim.Adam) -> None:
        """``optimizer.step()``; fused Adam as one direct kernel call (same arithmetic)."""
        fused_adam_step(optimizer) if self.optimizer_impl == "fused" else optimizer.step()

    def pieces(self) -> dict[str, tuple[bool, str | None]]:
        """Which of the update's fast pieces run (:meth:`Learner.pieces
        <torchrl_esrl.objectives.learner.Learner.pieces>`): the hand-written loss unless it hands
        over to ``TD3Loss`` (and why), the foreach soft update, fused Adam."""
        refusal = getattr(self.loss, "refusal", None)
        why = refusal() if callable(refusal) else None
        return {
            "td3_loss": (isinstance(self.loss, ManualGradTD3Loss) and why is None, why),
            "soft_update": (isinstance(self.target_update, ForeachSoftUpdate), None),
            "adam": (self.optimizer_impl == "fused", None),
        }

    def metrics(self) -> dict[str, float]:
        """None of its own (:class:`~torchrl_esrl.objectives.learner.Learner`)."""
        return {}

    def state_dict(self) -> dict:
        return {
            "loss": self.loss.state_dict(),
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "updates": self.updates,
        }

    def load_state_dict(self, state: dict) -> None:
        self.loss.load_state_dict(state["loss"])
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state["critic_optimizer"])
        self.updates = int(state["updates"])


# ------------------------------------------------------------ built from the config (recipes)
BF16_WARNING = (
    "warning: td3.precision=bf16 runs the TD3 actor's tanh squash in bfloat16, whose gradient is exactly 0 once the "
    "actor saturates, so the actor can stop learning: not for results (docs/deviations.md, 39)"
)


def make_td3(cfg, actor, critic, action_spec, pieces: Collection[str] | None = None) -> TD3:
    """TD3 of the ``td3`` section, with the fast pieces chosen (:mod:`torchrl_esrl.run.implementation`);
    with ``td3.random_frames`` > 0 its behaviour policy acts uniformly at random for that many
    frames first (Fujimoto's ``start_timesteps``, :class:`RandomWarmup`)."""
    c, fast = cfg.td3, chosen_pieces(cfg, pieces)
    td3 = TD3(
        actor,
        critic,
        action_spec.to(cfg.device),
        lr=c.lr,
        gamma=c.gamma,
        tau=c.tau,
        policy_noise=c.policy_noise,
        noise_clip=c.noise_clip,
        policy_delay=c.policy_delay,
        exploration_noise=c.exploration_noise,
        loss_function=c.loss_function,
        loss_class=ManualGradTD3Loss if "td3_loss" in fast else TD3Loss,  # it hands over to TD3Loss's autograd where it cannot compute exactly
        target_update_class=ForeachSoftUpdate if "soft_update" in fast else SoftUpdate,
        optimizer_impl="fused" if "adam" in fast else "default",
        num_threads=c.num_threads if c.num_threads is not None else job_cores(),
        precision=c.precision,
    )
    if c.precision == "bf16":
        run_record.warning(BF16_WARNING)
        print(BF16_WARNING, file=sys.stderr, flush=True)
    if c.random_frames > 0:
        td3.exploration_policy = RandomWarmup(td3.exploration_policy, action_spec, c.random_frames, seed=int(cfg.seed) + 3)
    return td3


def td3_holdings(cfg, sizes) -> list[Holding]:
    """:func:`make_td3`'s networks and optimiser states (:attr:`TD3.HELD_ACTOR_COPIES`, ...), for
    the run's memory estimate (:mod:`torchrl_esrl.run.capacity`)."""
    critic = mlp_parameters([sizes.observation_dim + sizes.action_dim, *cfg.td3.critic_hidden, 1])
    return [network_holding(TD3.HELD_ACTOR_COPIES, actor_parameters(cfg, sizes), NETWORK_FIELD), network_holding(TD3.HELD_CRITIC_COPIES, critic, NETWORK_FIELD)]
