"""numpy views of CPU tensors, for the one-row and few-row copies of the replay buffers.

numpy's indexing and slice copies skip torch's per-call dispatch, which dominates on tensors of a
few hundred elements (``python -m benchmarks.td3_frame`` times the frame they serve); the views
share the tensors' memory, so writing through them is writing the tensors.
"""
from __future__ import annotations

import numpy as np


def numpy_views(tensors) -> list[np.ndarray] | None:
    """Each tensor's memory as a numpy array, or None if one cannot be viewed so (a tensor on
    another device, of a dtype numpy lacks, or that requires grad)."""
    try:
        return [tensor.numpy() for tensor in tensors]
    except (TypeError, RuntimeError):
        return None
