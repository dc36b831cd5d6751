"""The ES collector (paper, Algorithms 1 and 2 "Evaluate"): every offspring plays one full
episode; its return is its fitness and its trajectory feeds the good/bad buffers.

:class:`ESCollector` evaluates a whole population ``params[P, D]`` and returns a
:class:`~torchrl_esrl.collectors.generation.Generation`. Backends do the stepping; they are
named in :mod:`torchrl_esrl.collectors.backends`.
"""
from __future__ import annotations

from collections.abc import Collection, Sequence

import numpy as np
import torch

from torchrl_esrl.collectors.backends import backend_class, es_backend, refusals, resolve_backend
from torchrl_esrl.collectors.generation import Generation
from torchrl_esrl.envs import EnvSpec, as_env_spec
from torchrl_esrl.modules.networks import cpu_actor
from torchrl_esrl.modules.population import Mirrored, ModulePopulation, es_population
from torchrl_esrl.run.implementation import chosen_pieces


class ESCollector:
    """Evaluates populations of actors for one full episode each (fitness = episode return).

    Args:
        env: the task: an :class:`~torchrl_esrl.envs.EnvSpec` (keyword arguments, wrappers,
            transforms), or a short name (``halfcheetah``) or gymnasium id.
        actor: the actor built by :func:`torchrl_esrl.modules.networks.make_actor` (its architecture and
            action bounds define every member).
        backend: a name in :data:`~torchrl_esrl.collectors.backends.BACKENDS`, or ``"auto"``
            (:func:`~torchrl_esrl.collectors.backends.resolve_backend`: the fastest for the task
            and the members' forward).
        max_episode_steps: episode length limit (the env's own when None).
        seed: seeds the stream of episode seeds (one fresh reset seed per member and call).
        population: the class that computes the members' actions from their flat parameters:
            :class:`~torchrl_esrl.modules.population.ModulePopulation` (the reference: ``actor``
            itself through ``functional_call``) or
            :class:`~torchrl_esrl.modules.population.PopulationActor` (one batched forward, which
            also reads OpenAI-ES's mirrored pairs; it refuses actors it cannot compute exactly).
    """

    def __init__(self, env: "str | EnvSpec", actor, backend: str = "auto", max_episode_steps: int | None = None, seed: int = 0, population=ModulePopulation, **backend_kwargs):
        self.env = as_env_spec(env, max_episode_steps)
        self.env_id = self.env.id
        self.population_actor = population(actor)
        # Per local backend, why it cannot play this env and these members as the gym reference
        # would, decided here, once (a module's state may change what a later probe finds).
        self.refusals = refusals(self.env, self.population_actor)
        backend = resolve_backend(backend, self.env, population_actor=self.population_actor)
        self.backend = backend_class(backend)(self.env, self.population_actor, **backend_kwargs)
        self.seeds = np.random.default_rng(seed)
        self.frames = 0

    def evaluate(self, params: torch.Tensor, seeds: Sequence[int] | None = None, mirrored: Mirrored | None = None) -> Generation:
        """Play one episode per row of ``params`` ([P, D], or [D] for a single actor).

        ``mirrored``: the same population as mirrored pairs (OpenAI-ES's antithetic sampling,
        :meth:`~torchrl_esrl.es.openes.OpenES.mirrored`); a backend that can use it reads each
        pair's noise once per step. The rows of ``params`` stay what is evaluated."""
        if mirrored is not None and not mirrored.matches(params):
            raise ValueError("mirrored: its center +- offsets are not the rows of params (member k and P/2 + k)")
        if not self.population_actor.mirrored_pairs:  # the flat rows are what is evaluated
            mirrored = None
        params = params.detach().float()
        if params.dim() == 1:
            params = params.unsqueeze(0)
        if params.shape[1] != self.population_actor.num_parameters:
            raise ValueError(f"expected {self.population_actor.num_parameters} parameters per member, got {params.shape[1]}")
        if seeds is None:
            seeds = self.seeds.integers(0, 2**31 - 1, size=params.shape[0]).tolist()
        generation = self.backend.rollout(params.contiguous(), seeds, mirrored=mirrored)
        self.frames += generation.frames
        return generation

    def evaluate_policy(self, vector: torch.Tensor, episodes: int, seeds: Sequence[int] | None = None) -> Generation:
        """Deterministic evaluation of one actor (flat parameters) over ``episodes`` episodes.

        These frames are evaluation frames, not ES frames: they are not added to ``frames``.
        """
        frames = self.frames
        generation = self.evaluate(vector.reshape(1, -1).expand(episodes, -1), seeds)
        self.frames = frames
        return generation

    def state_dict(self) -> dict:
        return {"seeds": self.seeds.bit_generator.state, "frames": self.frames}

    def load_state_dict(self, state: dict) -> None:
        self.seeds.bit_generator.state = state["seeds"]
        self.frames = int(state["frames"])


def make_es_collector(cfg, actor, pieces: Collection[str] | None = None) -> ESCollector:
    """The ES collector of a config: ``actor``'s architecture on the backend of
    :func:`~torchrl_esrl.collectors.backends.es_backend`, with the fast pieces chosen
    (:mod:`torchrl_esrl.run.implementation`), on the population's seed stream (``seed + 2``)."""
    fast = chosen_pieces(cfg, pieces)
    actor = cpu_actor(actor)
    population = es_population(actor, fast)
    backend, backend_kwargs = es_backend(cfg, fast, population(actor))  # the backend plays what the members' forward computes
    return ESCollector(EnvSpec.from_config(cfg.env), actor, backend=backend, seed=int(cfg.seed) + 2, population=population, **backend_kwargs)


def make_evaluator(cfg, actor, pieces: Collection[str] | None = None) -> ESCollector:
    """The deterministic evaluation of a recipe's policies: ``actor``'s architecture played in
    gymnasium (the ``gym`` backend), on the evaluation seed stream (``seed + 1000``)."""
    actor = cpu_actor(actor)
    population = es_population(actor, chosen_pieces(cfg, pieces))
    return ESCollector(EnvSpec.from_config(cfg.env), actor, backend="gym", seed=int(cfg.seed) + 1000, population=population)
