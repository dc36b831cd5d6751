"""Per-phase torch thread counts, and a job's share of the cores (docs/performance.md, "The fast pieces").

OpenMP's wait policy is fixed when torch loads (libgomp's default, spinning), but torch's intra-op
thread count can change at any time. Each phase runs with the count that suits its work:
:func:`torch_threads` sets it for a ``with`` block and restores the caller's afterwards;
:class:`RunThreads` is the run's own count, the one between its phases, kept with its checkpoint;
:func:`job_cores` is how many cores a job may use when a launcher or a script runs several at once.
"""
from __future__ import annotations

import os
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


class RunThreads:
    """The run's torch thread count between its phases, the count every :func:`torch_threads` block
    returns to: taken when the run starts, saved with its checkpoints (``state_dict``) and set again
    when one is restored (``load_state_dict``).

    A reduction over many elements (a matrix-vector product, the mean of a long vector) can round
    differently under another thread count. A checkpoint written inside a phase (a stop between two
    gradient steps) must therefore hold this count, not the phase's: the resumed process computes
    what follows the phase under the count the uninterrupted one had there, whatever count the
    process itself started with.
    """

    def __init__(self):
        self.count = torch.get_num_threads()

    def state_dict(self) -> dict:
        return {"torch": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.count = int(state["torch"])
        torch.set_num_threads(self.count)


def process_cores() -> int:
    """The cores this process may run on (its CPU affinity: a Slurm allocation, ``taskset``)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


JOBS_VARIABLE = "TORCHRL_ESRL_JOBS"  # jobs started side by side by a script (xargs -P, GNU parallel)


def concurrent_jobs(cores: int) -> int:
    """How many jobs run at once on this machine: ``$TORCHRL_ESRL_JOBS`` where a script that starts
    jobs side by side sets it, else joblib's ``n_jobs`` in a Hydra multirun (negative counts from the
    cores, as joblib does), else 1."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if os.environ.get(JOBS_VARIABLE):
        return max(1, int(os.environ[JOBS_VARIABLE]))
    if not HydraConfig.initialized():
        return 1
    hydra = HydraConfig.get()
    launcher = hydra.get("launcher") or {}
    if hydra.mode != RunMode.MULTIRUN or "joblib" not in str(launcher.get("_target_", "")).lower():
        return 1
    n_jobs = int(launcher.get("n_jobs") or 1)
    return max(1, n_jobs if n_jobs > 0 else cores + 1 + n_jobs)


def job_cores(cores: int | None = None) -> int:
    """This job's share of ``cores`` (default: :func:`process_cores`), divided among the jobs a
    launcher runs at once beside it (two joblib jobs on 2 cores: one each; on 64 cores: 32 each),
    so parallel jobs never oversubscribe. It is the default of ``td3.num_threads`` and of the
    ``mujoco_batch`` ES backend's threads."""
    cores = process_cores() if cores is None else int(cores)
    return max(1, cores // concurrent_jobs(cores))
