"""The chain rule through the hand-written MLPs of :mod:`torchrl_esrl.objectives.manual_grad`: the
forward of ``(weight, bias, activation)`` layers (``addmm`` for one network, ``baddbmm`` for the twin
critics' stacked parameters) and its backward, ``dW = g^T x``, ``db = sum_B g``, ``g <- (g W) * act'(x)``,
with the hidden activations' kernels and their derivatives as autograd computes them.
"""
from __future__ import annotations

import numpy as np
import torch


def tanh(x: torch.Tensor) -> torch.Tensor:
    """Hidden ``tanh`` of the hand-written forwards: numpy's kernel, in place on ``x`` (a fresh layer
    output) where no gradient is recorded; ``torch.tanh`` otherwise.

    numpy's kernel because torch 2.13's CPU ``tanh`` is slower than ``numpy.tanh`` on the update's
    256x256 float32 activations (``python -m benchmarks.td3_update`` times the update); the two
    agree to one float32 rounding step (tests/test_mlp_chain_rule.py).
    """
    if x.device.type != "cpu" or x.dtype not in (torch.float32, torch.float64) or (torch.is_grad_enabled() and x.requires_grad):
        return torch.tanh(x)
    array = x.numpy()
    np.tanh(array, out=array)
    return x


def relu(x: torch.Tensor) -> torch.Tensor:
    """Hidden ReLU of the hand-written forwards: in place on ``x`` (a fresh layer output) where no
    gradient is recorded, ``torch.relu`` otherwise (the same values)."""
    return torch.relu(x) if torch.is_grad_enabled() and x.requires_grad else x.relu_()


ACTIVATIONS = {"tanh": tanh, "relu": relu, None: None}  # the kernels of FAST_ACTIVATIONS (None: no activation)
# d activation: (gradient w.r.t. the output, the output) -> gradient w.r.t. the input, as autograd computes it (None: none)
ACTIVATION_BACKWARD = {tanh: torch.ops.aten.tanh_backward, relu: lambda grad, out: torch.ops.aten.threshold_backward(grad, out, 0), None: lambda grad, out: grad}


def layers(parameters, activations) -> list:
    """``(weight, bias, activation)`` per layer from ``(w_1, b_1, w_2, b_2, ...)``."""
    return [(parameters[2 * index], parameters[2 * index + 1], act) for index, act in enumerate(activations)]


def cast_tensors(tensors, dtype: torch.dtype | None) -> tuple:
    """``tensors`` in ``dtype`` (None: as they are; None entries stay None)."""
    if dtype is None:
        return tuple(tensors)
    return tuple(None if tensor is None else tensor.to(dtype) for tensor in tensors)


def cast(layers, dtype: torch.dtype | None) -> list:
    """``(weight, bias, activation)`` layers with weight and bias in ``dtype`` (None: ``layers`` itself)."""
    if dtype is None:
        return layers
    return [(weight.to(dtype), bias.to(dtype), act) for weight, bias, act in layers]


def stacked(layers, observation, action) -> torch.Tensor:
    """``[2, B]`` values of the stacked critics: one ``baddbmm`` per layer."""
    x = torch.cat([observation, action], -1)
    return forward(layers, x.expand(layers[0][0].shape[0], *x.shape)).squeeze(-1)


def forward(layers, x: torch.Tensor, inputs: list | None = None) -> torch.Tensor:
    """``x`` through ``(weight, bias, activation)`` layers: ``addmm`` for a network's ``[out, in]``
    weights, ``baddbmm`` for the twin critics' stacked ``[2, out, in]``, in the weights' dtype (``x``
    is cast to it). ``inputs`` (if given) receives each layer's input, which :func:`backward` needs."""
    if x.dtype != layers[0][0].dtype:
        x = x.to(layers[0][0].dtype)
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


def backward(layers, inputs: list, grad: torch.Tensor, needs, input_grad: bool = False) -> tuple[list, torch.Tensor | None]:
    """The chain rule back through :func:`forward`'s ``layers`` from ``grad`` = dL/d(output): per layer
    ``dW = g^T x`` and ``db = sum over the batch of g`` where ``needs`` (one flag per weight and bias)
    asks for them, then ``g <- (g W) * act'(x)`` while a layer below (or, with ``input_grad``, the
    input) needs it. Returns (the parameters' gradients, None where not asked; dL/d input or None)."""
    grads = [None] * len(needs)
    lowest = 0 if input_grad else next((index // 2 for index, need in enumerate(needs) if need), len(layers))
    for index in range(len(layers) - 1, lowest - 1, -1):
        weight = layers[index][0]
        if needs[2 * index]:
            grads[2 * index] = torch.matmul(grad.transpose(-2, -1), inputs[index])
        if needs[2 * index + 1]:
            grads[2 * index + 1] = grad.sum(-2)
        if index > lowest or input_grad:
            grad = torch.matmul(grad, weight)
            if index:
                grad = ACTIVATION_BACKWARD[layers[index - 1][2]](grad, inputs[index])
    return grads, grad if input_grad else None
