"""The hand-written TD3 loss of the fast path (``td3_loss`` in :data:`torchrl_esrl.run.implementation.FAST_PIECES`).

:class:`ManualGradTD3Loss` is TorchRL's :class:`~torchrl.objectives.TD3Loss` (Fujimoto et al.
2018) whose losses are ``torch.autograd.Function``s with the gradients written by the chain rule,
beneath ``loss.backward()``; :class:`TD3LossQ1Actor` is ``TD3Loss`` with Fujimoto's Q1-only actor
loss. :class:`torchrl_esrl.objectives.td3.TD3` trains either, or stock ``TD3Loss``.
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch.autograd.function import once_differentiable
from torchrl.modules import MLP, ValueOperator
from torchrl.objectives import TD3Loss
from torchrl.objectives.value import TD0Estimator

from torchrl_esrl.modules.networks import describe_actor, describe_mlp, squash
from torchrl_esrl.objectives import mlp_chain_rule as chain
from torchrl_esrl.torchrl_private import (
    backward_node_class, detached_qvalue_params, function_apply, gradient_hooks, has_entry, loss_priority_weight,
    module_hook_dicts, module_hooks, overridden_td3_loss_internals, reduce_loss, reweights_or_masks, td3_loss_default_keys,
    without_loss_contexts,
)


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


class ManualGradTD3Loss(TD3Loss):
    """TorchRL's ``TD3Loss`` (Fujimoto et al. 2018) with hand-written forwards and gradients.

    ``value_loss`` and ``actor_loss`` return loss tensors made by :class:`_CriticLoss` and
    :class:`_ActorLoss`, ``torch.autograd.Function`` s whose forward computes TD3Loss's loss
    (the twin critics' stacked ``[2, ...]`` parameters as one ``torch.baddbmm`` per layer, the
    actors as chains of ``torch.addmm``, the actor loss on the first critic only, as Fujimoto's
    TD3 and :class:`TD3LossQ1Actor`) and whose backward returns the parameter gradients by the
    chain rule. Autograd puts them into ``.grad``, so ``loss.backward()``, extra loss terms, hooks,
    gradient clipping and frozen parameters behave as with ``TD3Loss``. The arithmetic is
    TD3Loss's: the same noise draw (same RNG order), clamp to the action bounds, ``min`` of the
    target critics, TD(0) target ``r + gamma * (1 - terminated) * Q'``, squared error summed over
    the critics and averaged over the batch (tests/test_td3.py: losses, gradients and parameters
    against ``TD3Loss`` to float32 rounding).

    It runs only where it computes the function ``TD3Loss`` would (float32 rounding apart); elsewhere
    (see :meth:`refusal`) both losses are ``TD3Loss``'s own code and autograd. A subclass's
    ``value_loss`` or ``actor_loss`` that builds on ``super()``'s loss is trained through these
    gradients, as through autograd's.
    """

    def refusal(self, tensordict: TensorDictBase | None = None) -> str | None:
        """None where :meth:`value_loss` and :meth:`actor_loss` run the hand-written gradients,
        else why they hand over to ``TD3Loss``, in a few words (``"num_qvalue_nets=3"``; the run
        prints ``td3_loss: reference (num_qvalue_nets=3)``); with a batch, also that batch's reasons
        (prioritised weights...).

        The hand-written path needs: 2 critics, ``l2`` loss, ``mean`` reduction, a plain
        ``TD0Estimator``, TorchRL's default tensor keys, target networks for actor and critics, an
        actor of biased Linear layers with tanh or ReLU between them followed by ``TanhModule``, a
        critic ``MLP`` of the same kind over ``cat(observation, action)``, no module hooks, no
        autocast other than to bfloat16 (under which it computes as :meth:`matmul_dtype` says), no
        subclass override of the TD3Loss members it replaces; and a flat batch without
        prioritised weights, loss masks, ``steps_to_next_obs`` or inputs that need gradients.
        """
        reason = self._refusal(tensordict)
        if reason is None and tensordict is not None and self._needs_gradient(*(tensordict.get(key) for key in ("observation", "action", ("next", "reward")))):
            reason = "batch tensors that need gradients"
        return reason

    def value_loss(self, tensordict) -> tuple[torch.Tensor, dict]:
        """TD3Loss's critic loss and metadata; its gradient is :class:`_CriticLoss`'s."""
        if self._refusal(tensordict) is not None:
            return super().value_loss(tensordict)
        observation, action, reward = tensordict.get("observation"), tensordict.get("action"), tensordict.get(("next", "reward"))
        if self._needs_gradient(observation, action, reward):
            return super().value_loss(tensordict)
        layout, dtype = self._manual_layout(), self.matmul_dtype()
        noise = (torch.randn_like(action) * self.policy_noise).clamp(-self.noise_clip, self.noise_clip)  # first, as TD3Loss
        with torch.no_grad():
            next_observation = tensordict.get(("next", "observation"))
            x = squash(self.actor_network.module[1], chain.forward(chain.cast(layout.target_actor, dtype), next_observation), *layout.target_bounds)
            next_action = (x + noise).clamp(self.min_action, self.max_action)
            next_value = chain.stacked(chain.cast(layout.target_critics, dtype), next_observation, next_action).min(0)[0].unsqueeze(-1)
            terminated = tensordict.get(("next", "terminated"), default=tensordict.get(("next", "done")))
            target_value = (reward + self.value_estimator.gamma * (~terminated).int() * next_value).squeeze(-1)
        x = torch.cat([observation, action], -1)
        loss, current_qvalue, td_error = function_apply(_CriticLoss, (layout.critic_activations, dtype), x, target_value, *layout.critic_parameters)
        return loss, {"td_error": td_error, "next_state_value": next_value.squeeze(-1), "pred_value": current_qvalue, "target_value": target_value}

    def actor_loss(self, tensordict) -> tuple[torch.Tensor, dict]:
        """``-Q_1(s, pi(s)).mean()``: TD3Loss's actor loss (it keeps ``Q[0]`` of both critics), with
        the first critic's parameters detached; its gradient is :class:`_ActorLoss`'s."""
        if self._refusal(tensordict) is not None:
            return super().actor_loss(tensordict)
        observation = tensordict.get("observation")
        if self._needs_gradient(observation):
            return super().actor_loss(tensordict)
        layout, dtype = self._manual_layout(), self.matmul_dtype()
        low, high, critic1 = layout.actor_constants
        constants = (low, high, chain.cast(critic1, dtype))
        loss, state_action_value = function_apply(_ActorLoss, (*layout.actor_spec, dtype), constants, observation, *layout.actor_parameters)
        return loss, {"state_action_value_actor": state_action_value}

    def _refusal(self, tensordict) -> str | None:
        """:meth:`refusal`'s reason without the prefix (cheap: the networks are described once)."""
        layout = self._manual_layout()
        if isinstance(layout, str):
            return layout
        if self.loss_function != "l2":
            return f"loss_function={self.loss_function}"
        if self.reduction != "mean":
            return f"reduction={self.reduction}"
        if self.tensor_keys != td3_loss_default_keys():
            return "tensor keys other than TD3Loss's defaults"
        estimator = self.value_estimator
        if type(estimator) is not TD0Estimator:
            return f"value estimator {type(estimator).__name__}"
        if estimator.average_rewards:
            return "average_rewards"
        keys = estimator.tensor_keys
        if (keys.reward, keys.done, keys.terminated) != ("reward", "done", "terminated"):
            return "value estimator keys other than the defaults"
        if module_hooks(layout.hook_dicts):
            return "module hooks"
        if torch.is_autocast_enabled(layout.device_type) and self.matmul_dtype() is None:
            return f"autocast to {str(torch.get_autocast_dtype(layout.device_type)).removeprefix('torch.')}"
        if tensordict is None:
            return None
        if reweights_or_masks(self, tensordict):
            return "prioritised weights or loss mask"
        if tensordict.batch_dims != 1:
            return f"batch of {tensordict.batch_dims} dims"
        if has_entry(tensordict, keys.steps_to_next_obs):
            return "steps_to_next_obs"
        return None

    def matmul_dtype(self) -> torch.dtype | None:
        """``torch.bfloat16`` inside ``torch.autocast(..., dtype=torch.bfloat16)`` (``TD3(precision="bf16")``):
        the matrix products, the hidden activations and their gradients in bfloat16, as autocast runs
        ``TD3Loss``, the losses, the TD target and the parameters' gradients in their own float32;
        None otherwise (the parameters' own dtype throughout)."""
        device_type = self._manual_layout().device_type
        if torch.is_autocast_enabled(device_type) and torch.get_autocast_dtype(device_type) == torch.bfloat16:
            return torch.bfloat16
        return None

    @staticmethod
    def _needs_gradient(*tensors) -> bool:
        """Whether a batch tensor needs a gradient (TD3Loss would give it one, the hand-written gradients do not)."""
        return any(tensor.requires_grad for tensor in tensors)

    def _manual_layout(self):
        """The networks as :class:`_ManualGradLayout`, built once (TorchRL keeps the parameters in place
        for the life of the loss, as :class:`ForeachSoftUpdate` relies on too), or the reason the
        hand-written path does not apply to them."""
        layout = self.__dict__.get("_manual")
        if layout is None:
            layout = self.__dict__["_manual"] = self._describe()
        return layout

    def _describe(self):
        """:meth:`_manual_layout`'s value."""
        if self.num_qvalue_nets != 2:
            return f"num_qvalue_nets={self.num_qvalue_nets}"
        if not (self.delay_actor and self.delay_qvalue):
            return "no target actor or critic (delay_actor/delay_qvalue False)"
        overridden = overridden_td3_loss_internals(type(self), ManualGradTD3Loss)
        if overridden:
            return f"{type(self).__name__} overrides {overridden[0]}"
        actor, critic = describe_actor(self.actor_network), self.qvalue_network
        if isinstance(actor, str):
            return actor
        reason = actor.mlp.plain_refusal()
        if reason is not None:
            return f"actor MLP: {reason}"
        if not (
            type(critic) in (TensorDictModule, ValueOperator)
            and type(critic.module) is MLP  # its forward concatenates the in_keys
            and list(critic.in_keys) == ["observation", "action"]
            and list(critic.out_keys) == ["state_action_value"]
        ):
            return "critic is not an MLP over (observation, action) -> state_action_value"
        critic_mlp = describe_mlp(critic.module)
        reason = critic_mlp if isinstance(critic_mlp, str) else critic_mlp.plain_refusal()
        if reason is not None:
            return f"critic MLP: {reason}"
        return _ManualGradLayout(self, _named_kernels(actor.mlp), _named_kernels(critic_mlp))


without_loss_contexts(ManualGradTD3Loss, "value_loss", "actor_loss")


def _named_kernels(mlp) -> list[tuple[str, object]]:
    """``[(Linear's name, kernel of the activation after it or None), ...]`` of an MLP description."""
    return [(layer.name, chain.ACTIVATIONS[layer.activation]) for layer in mlp.layers]


class _CriticLoss(torch.autograd.Function):
    """TD3's critic loss ``sum_k mean_B (Q_k(s, a) - y)^2`` of the stacked critics (one ``baddbmm`` per
    layer for both) and its gradient by the chain rule from ``dL/dQ = 2 (Q - y) / B``.

    ``forward((activations, dtype), cat(s, a), y, w_1, b_1, w_2, ...)`` returns the loss, ``Q`` and the
    squared errors (the last two without gradient); ``backward`` the gradients of the parameters
    that need one (None for the others), scaled by the loss's incoming gradient. ``dtype`` (None: the
    parameters') is that of the products and activations; the errors are in ``y``'s.
    """

    @staticmethod
    def forward(ctx, spec, x, target, *parameters):
        activations, dtype = spec
        inputs = []
        computed = chain.cast_tensors(parameters, dtype)
        layers = chain.layers(computed, activations)
        current_qvalue = chain.forward(layers, x.expand(parameters[0].shape[0], *x.shape), inputs).squeeze(-1)
        error = current_qvalue - target
        td_error = error.pow(2)
        loss = td_error.sum(0).mean()
        ctx.save_for_backward(error, *computed, *inputs)  # autograd frees them after the backward
        ctx.activations, ctx.parameter_dtype = activations, parameters[0].dtype
        ctx.mark_non_differentiable(current_qvalue, td_error)
        ctx.set_materialize_grads(False)
        return loss, current_qvalue, td_error

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_loss, _grad_qvalue, _grad_td_error):
        _released(ctx)
        error, *saved = ctx.saved_tensors
        count = 2 * len(ctx.activations)
        if grad_loss is None:
            return (None,) * (3 + count)
        grad = ((error * (2.0 / error.shape[-1])).unsqueeze(-1) * grad_loss).to(saved[0].dtype)  # dL/dQ, [2, B, 1]
        grads, _ = chain.backward(chain.layers(saved[:count], ctx.activations), saved[count:], grad, ctx.needs_input_grad[3:])
        return None, None, None, *chain.cast_tensors(grads, ctx.parameter_dtype)


class _ActorLoss(torch.autograd.Function):
    """TD3's actor loss ``-mean_B Q_1(s, pi(s))`` and its gradient w.r.t. the actor's parameters: from
    ``dL/dQ_1 = -1/B`` back through the first critic (detached: its weights only carry the gradient)
    to the action, through ``TanhModule``'s squashing, then through the actor's layers.

    ``forward(spec, constants, s, *actor parameters)`` returns the loss and ``Q_1`` (without
    gradient); ``spec`` = (actor activations, TanhModule's ``clamp`` and ``non_trivial``, the dtype
    of the products and activations or None for the parameters'), ``constants`` = (action low,
    action high, the first critic's detached layers in that dtype).
    """

    @staticmethod
    def forward(ctx, spec, constants, observation, *parameters):
        activations, clamp, non_trivial, dtype = spec
        low, high, critic1 = constants
        actor_inputs, critic_inputs = [], []
        computed = chain.cast_tensors(parameters, dtype)
        squashed = chain.forward(chain.layers(computed, activations), observation, actor_inputs).tanh()  # squash(), step by step: its backward needs each step
        eps = torch.finfo(squashed.dtype).resolution
        clamped = squashed.clamp(-1 + eps, 1 - eps) if clamp else squashed
        action = low + (high - low) * (clamped + 1) / 2 if non_trivial else clamped
        state_action_value = chain.forward(critic1, torch.cat([observation, action], -1), critic_inputs).squeeze(-1).to(parameters[0].dtype)
        loss = -state_action_value.mean()
        ctx.save_for_backward(squashed, *computed, *actor_inputs, *critic_inputs)  # autograd frees them after the backward
        ctx.spec, ctx.constants, ctx.observation_dim, ctx.parameter_dtype = spec, constants, observation.shape[-1], parameters[0].dtype
        ctx.mark_non_differentiable(state_action_value)
        ctx.set_materialize_grads(False)
        return loss, state_action_value

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_loss, _grad_value):
        _released(ctx)
        activations, clamp, non_trivial, _ = ctx.spec
        low, high, critic1 = ctx.constants
        count = 2 * len(activations)
        squashed, *saved = ctx.saved_tensors
        parameters, actor_inputs, critic_inputs = saved[:count], saved[count : count + len(activations)], saved[count + len(activations) :]
        if grad_loss is None:
            return (None,) * (3 + count)
        batch = squashed.shape[0]
        grad = torch.full((batch, 1), -1.0 / batch, dtype=squashed.dtype, device=squashed.device) * grad_loss  # dL/dQ_1
        _, grad = chain.backward(critic1, critic_inputs, grad, (False,) * (2 * len(critic1)), input_grad=True)
        grad = grad[:, ctx.observation_dim :]  # dL/d action
        if non_trivial:
            grad = grad / 2 * (high - low)
        if clamp:
            eps = torch.finfo(squashed.dtype).resolution
            grad = torch.where((squashed >= -1 + eps) & (squashed <= 1 - eps), grad, 0.0)
        grad = torch.ops.aten.tanh_backward(grad.to(squashed.dtype), squashed)
        grads, _ = chain.backward(chain.layers(parameters, activations), actor_inputs, grad, ctx.needs_input_grad[3:])
        return None, None, None, *chain.cast_tensors(grads, ctx.parameter_dtype)


def _noting_hooks(function: type[torch.autograd.Function], outputs: int) -> type:
    """The class of ``function``'s graph nodes, made to note a hook registered on a node
    (``register_hook``, ``register_prehook``: torch keeps node hooks in C++ with no getter), so that
    :func:`backward` leaves such a node to the autograd engine; ``outputs``: the number of
    ``function``'s forward outputs."""
    node_class = backward_node_class(function)
    for name in ("register_hook", "register_prehook"):
        def register(node, hook, _register=getattr(node_class, name)):
            node.hooked = True
            return _register(node, hook)

        setattr(node_class, name, register)
    node_class.outputs = outputs
    return node_class


_LOSS_NODES = {_noting_hooks(_CriticLoss, 3): _CriticLoss, _noting_hooks(_ActorLoss, 2): _ActorLoss}  # node class: its Function


def backward(loss: torch.Tensor) -> None:
    """``loss.backward()``, the engine's work done here where it is only this: ``loss`` is the loss
    output of :class:`_CriticLoss` or :class:`_ActorLoss`, whose backward gives each parameter its
    gradient, which goes into an empty ``.grad``. Then that backward is called directly and its
    gradients are put into ``.grad`` as the engine would put them (the same tensors, tests/test_td3.py),
    without the engine's per-call bookkeeping. Anything more goes to ``loss.backward()``: an extra loss
    term, a ``.grad`` already there, a hook on the loss, its node or a parameter, a parameter that is
    not a leaf, anomaly detection."""
    node = loss.grad_fn
    function = _LOSS_NODES.get(type(node))
    leaves = _direct_leaves(loss, node) if function is not None else None
    if leaves is None:
        loss.backward()
        return
    # The Function's backward with the node as its context, as the engine calls it (once_differentiable:
    # without grad mode); the gradients have their parameters' shapes and dtypes (the engine's checks).
    grads = function.backward(node, torch.ones_like(loss), *(None,) * (node.outputs - 1))
    for leaf, grad in zip(leaves, grads[len(grads) - len(leaves) :]):  # the tensor inputs come last
        if leaf is not None and grad is not None:
            leaf.grad = grad if grad.stride() == leaf.stride() else torch.empty_like(leaf).copy_(grad)
    node.released = True  # as the engine frees the graph: a second backward through it fails


def _released(ctx) -> None:
    """Raise what the engine raises on a second backward through a graph it has freed, where
    :func:`backward` ran this node directly (its saved tensors stay until the loss is dropped)."""
    if getattr(ctx, "released", False):
        raise RuntimeError(
            "Trying to backward through the graph a second time (or directly access saved tensors after they have "
            "already been freed). Specify retain_graph=True if you need to backward through the graph a second time."
        )


def _direct_leaves(loss: torch.Tensor, node) -> list | None:
    """For :func:`backward`: the leaf tensor behind each tensor input of ``node`` (None for an input
    without gradient), or None where the engine must run (see there)."""
    if loss.output_nr != 0 or getattr(node, "hooked", False) or loss.retains_grad or gradient_hooks(loss) or torch.is_anomaly_enabled():
        return None
    leaves = []
    for next_node, _ in node.next_functions:
        leaf = None if next_node is None else getattr(next_node, "variable", None)  # AccumulateGrad's leaf
        if next_node is not None and (leaf is None or leaf.grad is not None or gradient_hooks(leaf)):
            return None
        leaves.append(leaf)
    return leaves


class _ManualGradLayout:
    """The tensors :class:`ManualGradTD3Loss` computes with, looked up once instead of ~30 TensorDict
    lookups per update: ``(w_1, b_1, ...)`` and activations of the actor and the stacked critics,
    ``(weight, bias, activation)`` layers of the target networks and of the first critic (detached,
    for the actor loss), the action bounds of both actors, the modules whose hooks would change
    the computation."""

    def __init__(self, loss: TD3Loss, actor_mlp, critic_mlp):
        def parameters(params, prefix, mlp):
            return tuple(params.get((*prefix, name, kind)) for name, _ in mlp for kind in ("weight", "bias"))

        actor_prefix = ("module", "0", "module")
        self.actor_parameters = parameters(loss.actor_network_params, actor_prefix, actor_mlp)
        self.target_actor = chain.layers(parameters(loss.target_actor_network_params, actor_prefix, actor_mlp), [act for _, act in actor_mlp])
        self.bounds, self.target_bounds = (
            (params.get(("module", "1", "action_low")), params.get(("module", "1", "action_high")))
            for params in (loss.actor_network_params, loss.target_actor_network_params)
        )
        self.critic_activations = tuple(act for _, act in critic_mlp)
        self.critic_parameters = parameters(loss.qvalue_network_params, ("module",), critic_mlp)
        self.target_critics = chain.layers(parameters(loss.target_qvalue_network_params, ("module",), critic_mlp), self.critic_activations)
        critic1 = chain.layers(tuple(p.detach()[0] for p in self.critic_parameters), self.critic_activations)
        self.actor_constants = (*self.bounds, critic1)
        tanh_module = loss.actor_network.module[1]
        self.actor_spec = (tuple(act for _, act in actor_mlp), bool(tanh_module.clamp), bool(tanh_module.non_trivial))
        self.hook_dicts = module_hook_dicts((*loss.actor_network.modules(), *loss.qvalue_network.modules()))
        self.device_type = self.critic_parameters[0].device.type
