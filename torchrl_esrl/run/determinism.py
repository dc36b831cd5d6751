"""Seeds and deterministic kernels: the same seed gives the same ``metrics.csv``."""
from __future__ import annotations

import os
import random

import numpy as np
import torch

# cuBLAS's workspace configuration under which its products are bitwise reproducible (PyTorch's
# "Reproducibility" notes; without it torch.use_deterministic_algorithms warns on every CUDA product).
CUBLAS_WORKSPACE_CONFIG = ":4096:8"


def seed_everything(seed: int) -> None:
    """Seed Python's, NumPy's and torch's global generators (torch's: CPU and every CUDA device)."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def make_deterministic() -> None:
    """Deterministic kernels: torch's deterministic algorithms, and on CUDA cuBLAS's fixed workspace
    (``CUBLAS_WORKSPACE_CONFIG``, unless the environment sets one), set before the run's first product.
    The CUDA generator's state is in every checkpoint (TorchRL's ``GlobalRNGState``); the run's thread
    count between phases is too (threads.RunThreads)."""
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", CUBLAS_WORKSPACE_CONFIG)
    torch.use_deterministic_algorithms(True, warn_only=True)
