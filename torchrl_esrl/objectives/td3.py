"""TD3 half of ES-TD3Buffers (paper, Algorithm 1 "perform TD3 iterations"; Fujimoto et al. 2018).

:class:`TD3` holds TorchRL's :class:`~torchrl.objectives.TD3Loss` (twin critics, target policy
smoothing), the :class:`~torchrl.objectives.SoftUpdate` of the targets, one Adam per network and
the policy delay; :func:`torchrl_esrl.algorithm.td3_phase.td3_phase` runs it inside Algorithm 1.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from tensordict import TensorDictBase
from tensordict.nn import TensorDictSequential
from torchrl.modules import AdditiveGaussianModule
from torchrl.objectives import SoftUpdate, TD3Loss

from torchrl_esrl.modules.networks import squash
from torchrl_esrl.torchrl_private import detached_qvalue_params, foreach_lerp_, fused_adam_step, loss_priority_weight, reduce_loss, reweights_or_masks, soft_update_tensors


class TD3LossQ1Actor(TD3Loss):
    """TorchRL's ``TD3Loss`` whose ``actor_loss`` evaluates only the first critic.

    ``TD3Loss.actor_loss`` runs both critics on ``(s, pi(s))`` (expand + vmap) and keeps
    ``Q[0]``: half of its critic forward and backward is thrown away. Fujimoto's TD3 (and this
    override) computes ``-Q_1(s, pi(s)).mean()`` only: the same loss value and gradients
    (tests/test_td3.py checks both against ``TD3Loss``), one critic pass less per actor update.
    Everything else (critic loss, target smoothing, target parameters) is ``TD3Loss``'s own.
    """

    def actor_loss(self, tensordict) -> tuple[torch.Tensor, dict]:
        weights = loss_priority_weight(self, tensordict)
        td = tensordict.select(*self.actor_network.in_keys, strict=False)
        with self.actor_network_params.to_module(self.actor_network, preserve_module_state=False):
            td = self.actor_network(td)
        td = td.select(*self.qvalue_network.in_keys, strict=False)
        with detached_qvalue_params(self)[0].to_module(self.qvalue_network, preserve_module_state=False):
            td = self.qvalue_network(td)
        state_action_value = td.get(self.tensor_keys.state_action_value).squeeze(-1)
        loss_actor = reduce_loss(self, -state_action_value, tensordict, weights)
        return loss_actor, {"state_action_value_actor": state_action_value.detach()}


def _plain_mlp(module: nn.Module):
    """``[(linear index, activation), ...]`` of an ``nn.Sequential`` of Linear layers and tanh/ReLU
    activations (TorchRL's ``MLP`` as built by :mod:`torchrl_esrl.modules.networks`), or None."""
    layers, children = [], list(module.named_children()) if isinstance(module, nn.Sequential) else None
    if not children:
        return None
    for name, child in children:
        if isinstance(child, nn.Linear):
            layers.append([name, None])
        elif type(child) in _ACTIVATIONS and layers and layers[-1][1] is None:
            layers[-1][1] = _ACTIVATIONS[type(child)]
        else:
            return None
    if any(act is None for _, act in layers[:-1]) or layers[-1][1] is not None:
        return None
    return [(name, act) for name, act in layers]


class _NumpyTanh(torch.autograd.Function):
    """``tanh`` computed by numpy, with torch's own ``tanh_backward`` (``grad * (1 - y^2)``).

    Written by hand because torch 2.13's CPU ``tanh`` measured slower than ``numpy.tanh`` on
    the update's 256x256 float32 activations (docs/performance.md). The two agree to one float32 rounding
    step; tests/test_td3.py compares the loss and its gradients with stock ``TD3Loss``.
    """

    @staticmethod
    def forward(ctx, x):
        y = torch.from_numpy(np.tanh(x.detach().numpy()))
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx, grad):
        (y,) = ctx.saved_tensors
        return torch.ops.aten.tanh_backward(grad, y)


def _tanh(x: torch.Tensor) -> torch.Tensor:
    """Hidden ``tanh`` of the hand-written losses: numpy's kernel, in place when no gradient is needed
    (``x`` is a fresh layer output there)."""
    if x.device.type != "cpu" or x.dtype not in (torch.float32, torch.float64):
        return torch.tanh(x)
    if torch.is_grad_enabled() and x.requires_grad:
        return _NumpyTanh.apply(x)
    array = x.numpy()
    np.tanh(array, out=array)
    return x


_ACTIVATIONS = {nn.Tanh: _tanh, nn.ReLU: torch.relu}
# d activation: (gradient w.r.t. the output, the output) -> gradient w.r.t. the input, as autograd computes it
_ACTIVATION_BACKWARD = {_tanh: torch.ops.aten.tanh_backward, torch.relu: lambda grad, out: torch.ops.aten.threshold_backward(grad, out, 0)}


class ManualGradTD3Loss(TD3LossQ1Actor):
    """TorchRL's ``TD3Loss`` (through :class:`TD3LossQ1Actor`) whose losses and gradients are
    written by hand: ``value_loss_backward`` and ``actor_loss_backward`` compute each loss and set
    its gradients by the chain rule, without autograd, and :class:`TD3` calls them.

    ``TD3Loss.value_loss`` evaluates the two critics (and their targets) with ``vmap`` over a
    TensorDict-expanded batch and the target actor through a parameter swap into the module;
    each step pays TensorDict and functorch bookkeeping around ~10 small matmuls. Here the
    critics' stacked parameters (TorchRL keeps them as ``[2, ...]`` tensors) are used directly:
    one ``torch.baddbmm`` over a ``[2, in, out]`` weight stack per layer for both critics, and
    the target actor as a chain of ``torch.addmm``. The arithmetic is TD3Loss's: same noise draw
    (same RNG order), clamp to the action bounds, ``min`` of the target critics, TD(0) target
    ``r + gamma * (1 - terminated) * Q'``, squared error summed over the critics and averaged
    over the batch (tests/test_td3.py compares losses, gradients and targets after several
    updates with stock ``TD3Loss``). ``actor_loss`` is :class:`TD3LossQ1Actor`'s, written the
    same way. Networks of another shape or activation, other value estimators, losses or
    reductions, prioritised weights or loss masks, and a subclass's own ``value_loss`` or
    ``actor_loss``, go to the parent's code and autograd.
    """

    def _manual_layout(self):
        """The networks as lists of ``(weight, bias, activation)`` tensors, built once (TorchRL
        keeps the parameters in place for the life of the loss, as :class:`ForeachSoftUpdate`
        relies on too), or False when the networks are not the plain MLPs this path handles."""
        layout = self.__dict__.get("_manual")
        if layout is None:
            layout = False
            actor, critic = self.actor_network, self.qvalue_network
            if (
                self.loss_function == "l2"
                and self.reduction == "mean"
                and type(self.value_estimator).__name__ == "TD0Estimator"
                and isinstance(actor, TensorDictSequential)
                and len(actor.module) == 2
                and type(actor.module[1]).__name__ == "TanhModule"
                and list(actor.in_keys) == ["observation"]
                and self.tensor_keys.action == "action"
            ):
                actor_mlp = _plain_mlp(actor.module[0].module)
                critic_mlp = _plain_mlp(getattr(critic, "module", None))
                if actor_mlp and critic_mlp and list(critic.in_keys) == ["observation", "action"] and len(critic.out_keys) == 1:
                    layout = _ManualGradLayout(self, actor_mlp, critic_mlp)
            self.__dict__["_manual"] = layout
        return layout

    def _manual_layout_for(self, tensordict):
        """:meth:`_manual_layout`, or False for a batch with prioritised weights or loss masks
        (TorchRL's code and autograd handle those)."""
        return False if reweights_or_masks(self, tensordict) else self._manual_layout()

    def _inherits(self, name: str) -> bool:
        """Whether ``name`` (``value_loss``, ``actor_loss``) is this class's own: a subclass that
        overrides it gets its own loss, through autograd, not the hand-written gradient of this one."""
        return getattr(type(self), name) is getattr(ManualGradTD3Loss, name)

    def value_loss(self, tensordict) -> tuple[torch.Tensor, dict]:
        """TD3Loss's critic loss and its metadata tensors (TD3.update uses :meth:`value_loss_backward`)."""
        layout = self._manual_layout_for(tensordict)
        if not layout:
            return super().value_loss(tensordict)
        action = tensordict.get(self.tensor_keys.action)
        target_value, next_value = self._target_value(layout, tensordict, action)
        current_qvalue = self._twin_critics(layout.critics, tensordict.get("observation"), action)
        loss_qval = (current_qvalue - target_value).pow(2).sum(0).mean()
        return loss_qval, {
            "td_error": (current_qvalue.detach() - target_value).pow(2),
            "next_state_value": next_value.squeeze(-1),
            "pred_value": current_qvalue.detach(),
            "target_value": target_value,
        }

    def value_loss_backward(self, tensordict) -> torch.Tensor | None:
        """``value_loss`` and its backward in one pass, without autograd: sets the critics'
        ``.grad`` (as ``zero_grad(set_to_none=True)`` then ``backward()`` would) and returns the
        loss. None where the hand-written path does not apply (the caller then uses ``value_loss``).

        Written by hand because autograd's graph bookkeeping around these small matmuls is a
        share of a TD3 update of the paper's networks (docs/performance.md, "td3_loss"); the gradient is
        the chain rule through the same ``bmm`` layers, layer by layer:
        ``dW = g^T x``, ``db = sum_batch g``, ``g <- (g W) * act'``, from
        ``g = dL/dQ = 2 (Q - y) / B``. tests/test_td3.py compares loss and gradients with
        stock ``TD3Loss.value_loss`` + ``backward``.
        """
        layout = self._manual_layout_for(tensordict) if self._inherits("value_loss") else False
        if not layout:
            return None
        action = tensordict.get(self.tensor_keys.action)
        target_value, _ = self._target_value(layout, tensordict, action)
        with torch.no_grad():
            inputs = []
            error = self._twin_critics(layout.critics, tensordict.get("observation"), action, inputs) - target_value  # [2, B]
            loss = error.pow(2).sum(0).mean()
            _backward(layout.critics, inputs, (error * (2.0 / error.shape[-1])).unsqueeze(-1))  # from dL/dQ, [2, B, 1]
        return loss

    def _target_value(self, layout, tensordict, action) -> tuple[torch.Tensor, torch.Tensor]:
        """TD3's target ``r + gamma (1 - terminated) min_k Q'_k(s', clamp(pi'(s') + noise))`` and the
        ``min`` term, with TD3Loss's noise draw (first, same RNG order)."""
        noise = (torch.randn_like(action) * self.policy_noise).clamp(-self.noise_clip, self.noise_clip)
        with torch.no_grad():
            next_observation = tensordict.get(("next", "observation"))
            x = self._actor(layout.target_actor, layout.target_bounds, next_observation)
            next_action = (x + noise).clamp(self.min_action, self.max_action)
            next_q = self._twin_critics(layout.target_critics, next_observation, next_action)
            next_value = next_q.min(0)[0].unsqueeze(-1)
            reward = tensordict.get(("next", "reward"))
            terminated = tensordict.get(("next", "terminated"), default=tensordict.get(("next", "done")))
            target_value = (reward + self.value_estimator.gamma * (~terminated).int() * next_value).squeeze(-1)
        return target_value, next_value

    def actor_loss(self, tensordict) -> tuple[torch.Tensor, dict]:
        """``-Q_1(s, pi(s)).mean()`` as :class:`TD3LossQ1Actor`, with the actor and the first
        critic's (detached) parameters used directly instead of swapped into the modules."""
        layout = self._manual_layout_for(tensordict)
        if not layout:
            return super().actor_loss(tensordict)
        observation = tensordict.get("observation")
        state_action_value = _forward(layout.critic1, torch.cat([observation, self._actor(layout.actor, layout.bounds, observation)], -1)).squeeze(-1)
        return -state_action_value.mean(), {"state_action_value_actor": state_action_value.detach()}

    def actor_loss_backward(self, tensordict) -> torch.Tensor | None:
        """``actor_loss`` and its backward in one pass, without autograd, as
        :meth:`value_loss_backward`: sets the actor's ``.grad`` and returns the loss (None where
        the hand-written path does not apply). From ``dL/dQ_1 = -1/B`` the gradient runs back through the
        first critic (its weights only carry it: they are not trained by this loss) to the action,
        through ``TanhModule``'s squashing, then through the actor's layers.
        tests/test_td3.py compares loss and gradients with stock ``TD3Loss.actor_loss``.
        """
        layout = self._manual_layout_for(tensordict) if self._inherits("actor_loss") else False
        if not layout:
            return None
        tanh_module = self.actor_network.module[1]
        with torch.no_grad():
            observation = tensordict.get("observation")
            actor_inputs, critic_inputs = [], []
            squashed = _forward(layout.actor, observation, actor_inputs).tanh()  # squash(), step by step: its backward needs each step
            low, high = layout.bounds
            eps = torch.finfo(squashed.dtype).resolution
            clamped = squashed.clamp(-1 + eps, 1 - eps) if tanh_module.clamp else squashed
            action = low + (high - low) * (clamped + 1) / 2 if tanh_module.non_trivial else clamped
            q1 = _forward(layout.critic1, torch.cat([observation, action], -1), critic_inputs)
            loss = -q1.squeeze(-1).mean()
            grad = _backward(layout.critic1, critic_inputs, torch.full_like(q1, -1.0 / q1.shape[0]), parameters=False)  # from dL/dQ_1
            grad = grad[:, observation.shape[-1]:]  # dL/d action
            if tanh_module.non_trivial:
                grad = grad / 2 * (high - low)
            if tanh_module.clamp:
                grad = torch.where((squashed >= -1 + eps) & (squashed <= 1 - eps), grad, 0.0)
            _backward(layout.actor, actor_inputs, torch.ops.aten.tanh_backward(grad, squashed))
        return loss

    def _actor(self, layers, bounds, observation) -> torch.Tensor:
        """The actor (MLP + ``TanhModule``) with the online or target ``layers``, as its modules compute it."""
        return squash(self.actor_network.module[1], _forward(layers, observation), *bounds)

    @staticmethod
    def _twin_critics(layers, observation, action, inputs: list | None = None) -> torch.Tensor:
        """``[2, B]`` values of the stacked critics: one ``baddbmm`` per layer."""
        x = torch.cat([observation, action], -1)
        return _forward(layers, x.expand(2, *x.shape), inputs).squeeze(-1)


def _forward(layers, x: torch.Tensor, inputs: list | None = None) -> torch.Tensor:
    """``x`` through ``(weight, bias, activation)`` layers: ``addmm`` for a network's ``[out, in]``
    weights, ``baddbmm`` for the twin critics' stacked ``[2, out, in]``. ``inputs`` (if given)
    receives each layer's input, which :func:`_backward` needs."""
    for weight, bias, act in layers:
        if inputs is not None:
            inputs.append(x)
        if weight.dim() == 2:
            x = torch.addmm(bias, x, weight.t())
        else:
            x = torch.baddbmm(bias.unsqueeze(1), x, weight.transpose(1, 2))
        if act is not None:
            x = act(x)
    return x


def _backward(layers, inputs: list, grad: torch.Tensor, parameters: bool = True) -> torch.Tensor:
    """The chain rule back through :func:`_forward`'s ``layers`` from ``grad`` = dL/d(output):
    per layer ``dW = g^T x`` and ``db = sum over the batch of g`` (assigned to ``.grad`` when
    ``parameters``), then ``g <- (g W) * act'(x)``. Returns dL/d(first input) when not
    ``parameters`` (the actor loss needs dL/d action from the first critic, whose weights it does
    not train); with ``parameters`` the first layer's input gradient is not computed."""
    for index in range(len(layers) - 1, -1, -1):
        weight, bias, _ = layers[index]
        if parameters:
            weight.grad = torch.matmul(grad.transpose(-2, -1), inputs[index])
            bias.grad = grad.sum(-2)
            if not index:
                break
        grad = torch.matmul(grad, weight)
        if index:
            grad = _ACTIVATION_BACKWARD[layers[index - 1][2]](grad, inputs[index])
    return grad


class _ManualGradLayout:
    """The tensors :class:`ManualGradTD3Loss` computes with, looked up once instead of ~30 TensorDict
    lookups per update: ``(weight, bias, activation)`` per layer of the online and target actor
    and twin critics, the first critic's detached weights for the actor loss, and
    the action bounds of both actors."""

    def __init__(self, loss: TD3Loss, actor_mlp, critic_mlp):
        def layers(params, prefix, mlp):
            return [(params.get((*prefix, name, "weight")), params.get((*prefix, name, "bias")), act) for name, act in mlp]

        actor_prefix = ("module", "0", "module")
        self.actor = layers(loss.actor_network_params, actor_prefix, actor_mlp)
        self.target_actor = layers(loss.target_actor_network_params, actor_prefix, actor_mlp)
        self.bounds, self.target_bounds = (
            (params.get(("module", "1", "action_low")), params.get(("module", "1", "action_high")))
            for params in (loss.actor_network_params, loss.target_actor_network_params)
        )
        self.critics = layers(loss.qvalue_network_params, ("module",), critic_mlp)
        self.target_critics = layers(loss.target_qvalue_network_params, ("module",), critic_mlp)
        self.critic1 = [(weight.detach()[0], bias.detach()[0], act) for weight, bias, act in self.critics]


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


class TD3:
    """TD3 learner over an actor and a critic template (two critics are made from it).

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
        loss_class: the ``TD3Loss`` class (or a subclass) to build. Stock ``TD3Loss`` (the
            reference, trained by autograd) or :class:`ManualGradTD3Loss`, whose
            ``value_loss_backward``/``actor_loss_backward`` give the same losses and gradients
            without autograd; :meth:`update` uses those methods where the loss has them.
        target_update_class: ``SoftUpdate`` (the reference) or :class:`ForeachSoftUpdate`.
        optimizer_impl: ``"default"`` (torch's ``Adam`` as constructed by default, the
            reference), ``"foreach"``, or ``"fused"`` (fused Adam, stepped by one direct kernel
            call: :func:`~torchrl_esrl.torchrl_private.fused_adam_step`).
        num_threads: torch threads while :func:`~torchrl_esrl.algorithm.td3_phase.td3_phase` runs
            (None: leave the process's count; docs/performance.md).

    The reference is TorchRL's stock TD3 (``TD3Loss``, ``SoftUpdate``, ``Adam``);
    :func:`torchrl_esrl.run.factories.make_td3` picks the fast pieces.
    """

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
        loss_class: type[TD3Loss] = TD3Loss,
        target_update_class: type[SoftUpdate] = SoftUpdate,
        optimizer_impl: str = "default",
        num_threads: int | None = None,
    ):
        self.actor = actor
        self.action_spec = action_spec
        self.loss = loss_class(
            actor_network=actor,
            qvalue_network=critic,
            action_spec=action_spec,
            num_qvalue_nets=2,
            policy_noise=policy_noise,
            noise_clip=noise_clip,
            loss_function=loss_function,
            delay_actor=True,
            delay_qvalue=True,
        )
        self.loss.make_value_estimator(gamma=gamma)
        self.target_update = target_update_class(self.loss, tau=tau)
        # The loss shares storage with `actor`; the two critics live in the loss's stacked params.
        if optimizer_impl not in ("fused", "foreach", "default"):
            raise ValueError(f"optimizer_impl must be fused, foreach or default, got {optimizer_impl!r}")
        self.optimizer_impl = optimizer_impl
        options = {"fused": {"fused": True}, "foreach": {"foreach": True}, "default": {}}[optimizer_impl]
        self.actor_optimizer = torch.optim.Adam(list(actor.parameters()), lr=lr, **options)
        self.critic_optimizer = torch.optim.Adam(list(self.loss.qvalue_network_params.values(True, True)), lr=lr, **options)
        self.policy_delay = int(policy_delay)
        self.exploration_policy = TensorDictSequential(
            actor,
            AdditiveGaussianModule(spec=action_spec, sigma_init=1.0, sigma_end=1.0, mean=0.0, std=float(exploration_noise)),
        )
        self.num_threads = num_threads
        self.updates = 0

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """One TD3 step: critic update; every ``policy_delay`` steps actor and target updates."""
        self.critic_optimizer.zero_grad(set_to_none=True)
        manual = getattr(self.loss, "value_loss_backward", None)  # loss and gradients in one pass, where the loss has it
        critic_loss = manual(batch) if manual is not None else None
        if critic_loss is None:
            critic_loss, _ = self.loss.value_loss(batch)
            critic_loss.backward()
        out = {"critic_loss": critic_loss.item()}
        if not math.isfinite(out["critic_loss"]):
            raise FloatingPointError(f"TD3 critic loss is {out['critic_loss']} at update {self.updates}")
        self._step(self.critic_optimizer)
        self.updates += 1
        if self.updates % self.policy_delay == 0:
            self.actor_optimizer.zero_grad(set_to_none=True)
            manual = getattr(self.loss, "actor_loss_backward", None)
            actor_loss = manual(batch) if manual is not None else None
            if actor_loss is None:
                actor_loss, _ = self.loss.actor_loss(batch)
                actor_loss.backward()
            out["actor_loss"] = actor_loss.item()
            if not math.isfinite(out["actor_loss"]):
                raise FloatingPointError(f"TD3 actor loss is {out['actor_loss']} at update {self.updates}")
            self._step(self.actor_optimizer)
            self.target_update.step()
        return out

    def _step(self, optimizer: torch.optim.Adam) -> None:
        """``optimizer.step()``; fused Adam as one direct kernel call (same arithmetic)."""
        fused_adam_step(optimizer) if self.optimizer_impl == "fused" else optimizer.step()

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
