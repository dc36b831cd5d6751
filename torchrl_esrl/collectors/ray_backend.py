"""ES offspring evaluated by Ray workers (paper, Algorithm 1 "Evaluate", spread over machines).

OpenAI-ES is embarrassingly parallel (Salimans et al. 2017): every offspring's episode is
independent. :class:`RayBackend` is an ES collector backend (``es.backend=ray``) that splits a
population ``params[P, D]`` and its reset seeds into contiguous shares, one per Ray actor; each
actor runs an ordinary *local* backend (``ray.worker_backend``: ``auto``, ``gym``,
``mujoco_batch``, ...) on its share, and the shares come back as :class:`Generation` s that are
concatenated in member order. ``collector/traj_ids`` is shifted to global member indices, so
the learner, its buffers and the ES update see exactly what a local backend would produce:
with the same seeds the generation is identical (``tests/test_ray_backend.py``). Given OpenAI-ES's
mirrored pairs, the shares are shares of pairs (members k and P/2 + k on one worker), so each
worker reads every pair's noise once per step as a local backend does.

Ray has no notion of "evaluate this batched population function over rows" that keeps the
member order and the TorchRL transition layout, hence this small hand-written scatter/gather.
Ray is an optional extra (``pip install -e ".[ray]"``); it is imported only when this backend
is built.
"""
from __future__ import annotations

import os
from collections.abc import Sequence

import torch

from torchrl_esrl.collectors.backends import LOCAL_BACKENDS, backend_class, resolve_backend
from torchrl_esrl.collectors.generation import Generation
from torchrl_esrl.modules.population import Mirrored, PopulationActor

TRAJ_IDS = ("collector", "traj_ids")


class _RolloutWorker:
    """Body of one Ray actor: a local ES backend over this worker's share of the population."""

    def __init__(self, env_id: str, population_actor: PopulationActor, max_episode_steps, backend: str, backend_kwargs: dict):
        torch.set_num_threads(max(1, int(backend_kwargs.pop("torch_threads", 1))))
        if backend not in LOCAL_BACKENDS:  # resolved by RayBackend
            raise ValueError(f"ray.worker_backend: '{backend}' is not a local backend (allowed: {', '.join(LOCAL_BACKENDS)})")
        self.backend_name = backend
        self.backend = backend_class(backend)(env_id, population_actor, max_episode_steps=max_episode_steps, **backend_kwargs)

    def name(self) -> str:
        return self.backend_name

    def node(self) -> str:
        import ray

        return ray.get_runtime_context().get_node_id()

    def rollout(self, params: torch.Tensor, seeds: list[int], mirrored: Mirrored | None = None) -> Generation:
        return self.backend.rollout(params, seeds, mirrored=mirrored)


# Shares start at multiples of this many members. Why: MKL's matrix-vector kernels round
# differently depending on the 64-byte alignment of their operands, so member p's actions are
# bitwise those of the local backend only if p keeps its offset modulo 64 bytes inside its
# share. 16 members of float32 rows are a multiple of 64 bytes for any parameter or observation
# size (a share starting at member 3 measured 1-ulp action differences that chaotic MuJoCo
# dynamics turn into different returns within 20 steps).
ALIGNED_MEMBERS = 16


def member_shares(population: int, workers: int, align: int = ALIGNED_MEMBERS) -> list[tuple[int, int]]:
    """Contiguous ``[start, stop)`` member ranges, one per worker, as even as blocks of ``align`` allow."""
    blocks = -(-population // align)
    edges = [min(population, align * (blocks * w // workers)) for w in range(workers + 1)]
    return list(zip(edges[:-1], edges[1:]))


def concatenate_generations(parts: Sequence[Generation]) -> Generation:
    """One Generation from consecutive shares of a population, with global member indices."""
    offset, transitions = 0, []
    for part in parts:
        td = part.transitions
        td.set(TRAJ_IDS, td.get(TRAJ_IDS) + offset)
        transitions.append(td)
        offset += part.returns.numel()
    return Generation(
        torch.cat([p.returns for p in parts]),
        torch.cat([p.lengths for p in parts]),
        torch.cat(transitions, 0),
    )


def connect(address: str | None = None, num_cpus: int | None = None, object_store_memory: int | None = None) -> bool:
    """Join the Ray cluster at ``address`` (``"auto"``, ``"host:port"``), or start a local one on
    127.0.0.1 when ``address`` is None. Returns True if this call started Ray."""
    import ray

    if ray.is_initialized():
        return False
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no phoning home from a training job
    kwargs: dict = {"include_dashboard": False, "log_to_driver": False, "ignore_reinit_error": True}
    if address:
        ray.init(address=address, **kwargs)
    else:
        ray.init(_node_ip_address="127.0.0.1", num_cpus=num_cpus, object_store_memory=object_store_memory, **kwargs)
    return True


class RayBackend:
    """ES collector backend whose rollouts run on ``num_workers`` Ray actors.

    Args:
        env_id, population_actor, max_episode_steps: as for every backend.
        address: Ray cluster address (``"auto"``, ``"host:port"``); None starts Ray on this machine.
        num_workers: Ray actors; each evaluates a contiguous share of every population.
        worker_backend: the local backend each actor runs (``auto`` picks the fastest for the env,
            :func:`~torchrl_esrl.collectors.backends.resolve_backend`).
        num_cpus_per_worker: CPUs Ray reserves for each actor (and torch threads it uses).
        worker_kwargs: extra keyword arguments of the worker backend (e.g. its thread count).
        spread: place actors on different nodes when possible (Ray's ``SPREAD`` strategy).
    """

    name = "ray"

    def __init__(
        self,
        env_id: str,
        population_actor: PopulationActor,
        max_episode_steps: int | None = None,
        *,
        num_workers: int,  # the values live in conf/config.yaml's ray section
        worker_backend: str,
        num_cpus_per_worker: float,
        address: str | None = None,
        worker_kwargs: dict | None = None,
        spread: bool = True,
        object_store_memory: int | None = None,
    ):
        import ray

        if num_workers < 1:
            raise ValueError(f"ray.num_workers must be a positive integer, got {num_workers}")
        worker_backend = resolve_backend(worker_backend, env_id, field="ray.worker_backend", allowed=LOCAL_BACKENDS)
        self.started_ray = connect(address, object_store_memory=object_store_memory)
        worker_kwargs = dict(worker_kwargs or {})
        worker_kwargs.setdefault("torch_threads", max(1, int(num_cpus_per_worker)))
        remote = ray.remote(num_cpus=num_cpus_per_worker, scheduling_strategy="SPREAD" if spread else "DEFAULT")(_RolloutWorker)
        self.workers = [remote.remote(env_id, population_actor, max_episode_steps, worker_backend, dict(worker_kwargs)) for _ in range(int(num_workers))]
        self.worker_backend = ray.get(self.workers[0].name.remote())  # fails here, not mid-training, on a bad backend

    def nodes(self) -> list[str]:
        """Ray node id of every worker (to check placement)."""
        import ray

        return ray.get([w.node.remote() for w in self.workers])

    def rollout(self, params: torch.Tensor, seeds: Sequence[int], mirrored: Mirrored | None = None) -> Generation:
        """Shares of ``params`` on the workers; with ``mirrored``, shares of its pairs."""
        import ray

        if mirrored is not None:
            return self._rollout_pairs(params, seeds, mirrored)

        seeds = [int(s) for s in seeds]
        futures = [
            worker.rollout.remote(params[start:stop].contiguous(), seeds[start:stop])
            for worker, (start, stop) in zip(self.workers, member_shares(params.shape[0], len(self.workers)))
            if stop > start
        ]
        return concatenate_generations(ray.get(futures))

    def _rollout_pairs(self, params: torch.Tensor, seeds: Sequence[int], mirrored: Mirrored) -> Generation:
        """Each worker evaluates pairs ``[a, b)``: members ``a..b-1`` and ``K+a..K+b-1`` as a
        population of its own; the halves come back in member order."""
        import ray

        seeds, pairs = [int(s) for s in seeds], mirrored.offsets.shape[0]
        shares = [(a, b) for a, b in member_shares(pairs, len(self.workers)) if b > a]
        futures = [
            worker.rollout.remote(
                torch.cat([params[a:b], params[pairs + a : pairs + b]]), seeds[a:b] + seeds[pairs + a : pairs + b],
                Mirrored(mirrored.center, mirrored.offsets[a:b].contiguous()),
            )
            for worker, (a, b) in zip(self.workers, shares)
        ]
        parts = [(part, b - a) for part, (a, b) in zip(ray.get(futures), shares)]
        return concatenate_generations([part.members(0, n) for part, n in parts] + [part.members(n, 2 * n) for part, n in parts])

    def close(self) -> None:
        """Stop the actors (and Ray itself if this backend started it)."""
        import ray

        for worker in self.workers:
            ray.kill(worker)
        self.workers = []
        if self.started_ray:
            ray.shutdown()


def make_ray_backend(env_id: str, population_actor: PopulationActor, max_episode_steps: int | None = None, **kwargs) -> RayBackend:
    return RayBackend(env_id, population_actor, max_episode_steps=max_episode_steps, **kwargs)
