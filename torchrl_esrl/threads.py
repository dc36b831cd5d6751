"""Per-phase torch thread counts (docs/performance.md, "Threads").

OpenMP's wait policy is fixed when torch loads (the recipes choose ``PASSIVE`` for the ES
phase's sake), but torch's intra-op thread count can change at any time. Each phase runs with
the count that suits its work: :func:`torch_threads` sets it for a ``with`` block and restores
the caller's afterwards.
"""
from __future__ import annotations

from contextlib import contextmanager

import torch


@contextmanager
def torch_threads(num_threads: int | None):
    """Run the block with ``torch.set_num_threads(num_threads)``; None leaves the count alone."""
    if num_threads is None:
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(int(num_threads))
    try:
        yield
    finally:
        torch.set_num_threads(before)
