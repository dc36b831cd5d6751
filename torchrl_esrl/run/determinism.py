"""Seeds and deterministic kernels: the same seed gives the same ``metrics.csv``."""
from __future__ import annotations

import random

import numpy as np
import torch


def seed_everything(seed: int) -> None:
    """Seed Python's, NumPy's and torch's global generators."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def make_deterministic() -> None:
    """Deterministic CPU kernels (the run's thread count between phases is part of the checkpoint: threads.RunThreads)."""
    torch.use_deterministic_algorithms(True, warn_only=True)
