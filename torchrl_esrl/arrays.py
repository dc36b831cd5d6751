"""numpy views of CPU tensors, for the one-row and few-row copies of the replay buffers.

numpy's indexing and slice copies cost ~0.2-1 us a call against ~2-4 us for torch's on tensors of
a few hundred elements (measured on the 2-core machine, docs/performance.md); the views share the
tensors' memory, so writing through them is writing the tensors.
"""
from __future__ import annotations

import numpy as np
import torch


def numpy_view(tensor: torch.Tensor) -> np.ndarray | None:
    """The tensor's memory as a numpy array; None for another device or a dtype numpy lacks."""
    if tensor.device.type != "cpu":
        return None
    try:
        return tensor.numpy()
    except (TypeError, RuntimeError):
        return None


def numpy_views(tensors) -> list[np.ndarray] | None:
    """:func:`numpy_view` of each tensor, or None if one has none (or requires grad)."""
    try:
        return [tensor.numpy() for tensor in tensors]
    except (TypeError, RuntimeError):  # another device, a dtype numpy lacks, a tensor that requires grad
        return None
