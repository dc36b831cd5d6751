"""The ES collector (paper, Algorithms 1 and 2 "Evaluate"): every offspring plays one full
episode; its return is its fitness and its trajectory feeds the good/bad buffers.

:class:`ESCollector` evaluates a whole population ``params[P, D]`` and returns a
:class:`Generation`: per-member returns and lengths, and all *real* transitions (members whose
episode ends early contribute only the steps they took) in TorchRL's layout::

    observation, action,
    next/{observation, reward, done, terminated, truncated},
    episode_return,            # the return of the episode the transition belongs to
    collector/traj_ids         # the member (offspring) index

Backends do the stepping. ``"gym"`` (this module) steps one gymnasium env per member in
lock-step with one batched policy forward per step: any gymnasium id works, and it is the
reference the fast backends are checked against.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_esrl.envs import make_gym_env, resolve_env_id
from torchrl_esrl.networks import PopulationActor


@dataclass
class Generation:
    """What one population evaluation produced."""

    returns: torch.Tensor  # [P] float64, undiscounted episode returns (the fitness)
    lengths: torch.Tensor  # [P] int64, steps of each episode
    transitions: TensorDict  # [sum(lengths)] flat, member-major, time-ordered within a member

    @property
    def frames(self) -> int:
        return int(self.lengths.sum())

    def member_mask(self, members: torch.Tensor) -> torch.Tensor:
        """Transition mask selecting the members where ``members[P]`` (bool) is True."""
        return members[self.transitions.get(("collector", "traj_ids"))]


def transitions_from_arrays(obs, actions, next_obs, rewards, terminated, truncated, lengths, returns) -> TensorDict:
    """Flatten padded ``[P, T, ...]`` numpy arrays into the TorchRL transition layout (real steps only)."""
    population, horizon = rewards.shape
    lengths_t = torch.as_tensor(lengths, dtype=torch.long)
    valid = torch.arange(horizon)[None, :] < lengths_t[:, None]  # [P, T]
    members = torch.arange(population)[:, None].expand(population, horizon)[valid]

    def take(array, dtype):
        return torch.as_tensor(array)[valid].to(dtype)

    reward = take(rewards, torch.float32).unsqueeze(-1)
    term = take(terminated, torch.bool).unsqueeze(-1)
    trunc = take(truncated, torch.bool).unsqueeze(-1)
    n = reward.shape[0]
    return TensorDict(
        {
            "observation": take(obs, torch.float32),
            "action": take(actions, torch.float32),
            "next": {
                "observation": take(next_obs, torch.float32),
                "reward": reward,
                "done": term | trunc,
                "terminated": term,
                "truncated": trunc,
            },
            "episode_return": torch.as_tensor(returns, dtype=torch.float32)[members].unsqueeze(-1),
            "collector": {"traj_ids": members},
        },
        batch_size=[n],
    )


class GymBackend:
    """Reference backend: P gymnasium envs stepped in lock-step, one batched forward per step."""

    name = "gym"

    def __init__(self, env_id: str, population_actor: PopulationActor, max_episode_steps: int | None = None):
        self.env_id = resolve_env_id(env_id)
        self.policy = population_actor
        self.max_episode_steps = max_episode_steps
        self.envs: list = []
        probe = self._env(0)
        self.horizon = int(probe.spec.max_episode_steps or 1000)
        self.observation_dim = int(np.prod(probe.observation_space.shape))
        self.action_dim = int(np.prod(probe.action_space.shape))

    def _env(self, i: int):
        while len(self.envs) <= i:
            self.envs.append(make_gym_env(self.env_id, self.max_episode_steps))
        return self.envs[i]

    def rollout(self, params: torch.Tensor, seeds: Sequence[int]) -> Generation:
        population, horizon = params.shape[0], self.horizon
        obs = np.zeros((population, horizon, self.observation_dim))
        next_obs = np.zeros_like(obs)
        actions = np.zeros((population, horizon, self.action_dim), dtype=np.float32)
        rewards = np.zeros((population, horizon))
        terminated = np.zeros((population, horizon), dtype=bool)
        truncated = np.zeros((population, horizon), dtype=bool)
        lengths = np.zeros(population, dtype=np.int64)
        current = np.stack([self._env(p).reset(seed=int(seeds[p]))[0] for p in range(population)])
        active = np.ones(population, dtype=bool)
        layers = self.policy.split(params)
        t = 0
        while active.any():
            # Finished members still get a (cheap) forward: slicing params would copy P x D floats.
            action = self.policy(params, torch.as_tensor(current, dtype=torch.float32), layers).numpy()
            for p in np.flatnonzero(active):
                o, r, term, trunc, _ = self.envs[p].step(action[p])
                obs[p, t], actions[p, t], next_obs[p, t], rewards[p, t] = current[p], action[p], o, r
                terminated[p, t], truncated[p, t] = term, trunc
                current[p] = o
                lengths[p] = t + 1
                if term or trunc:
                    active[p] = False
            t += 1
        returns = rewards.sum(axis=1)
        transitions = transitions_from_arrays(obs, actions, next_obs, rewards, terminated, truncated, lengths, returns)
        return Generation(torch.as_tensor(returns), torch.as_tensor(lengths), transitions)


def _ray_backend(*args, **kwargs):
    """``es.backend=ray``: imported on use, Ray is an optional extra (torchrl_esrl/ray_backend.py)."""
    from torchrl_esrl.ray_backend import make_ray_backend

    return make_ray_backend(*args, **kwargs)


BACKENDS: dict[str, Callable[..., object]] = {"gym": GymBackend, "ray": _ray_backend}


def available_backends() -> list[str]:
    return ["auto", *BACKENDS]


class ESCollector:
    """Evaluates populations of actors for one full episode each (fitness = episode return).

    Args:
        env_id: short name (``halfcheetah``) or gymnasium id.
        actor: the actor built by :func:`torchrl_esrl.networks.make_actor` (its architecture and
            action bounds define every member).
        backend: ``"auto"`` or a name in :data:`BACKENDS`.
        max_episode_steps: episode length limit (the env's own when None).
        seed: seeds the stream of episode seeds (one fresh reset seed per member and call).
    """

    def __init__(self, env_id: str, actor, backend: str = "auto", max_episode_steps: int | None = None, seed: int = 0, **backend_kwargs):
        self.env_id = resolve_env_id(env_id)
        self.population_actor = PopulationActor(actor)
        if backend == "auto":
            backend = default_backend(self.env_id)
        if backend not in BACKENDS:
            from torchrl_esrl.config import ConfigError

            raise ConfigError(f"es.backend: unknown backend '{backend}' (allowed: {', '.join(available_backends())})")
        self.backend = BACKENDS[backend](self.env_id, self.population_actor, max_episode_steps=max_episode_steps, **backend_kwargs)
        self.seeds = np.random.default_rng(seed)
        self.frames = 0

    def evaluate(self, params: torch.Tensor, seeds: Sequence[int] | None = None) -> Generation:
        """Play one episode per row of ``params`` ([P, D], or [D] for a single actor)."""
        params = params.detach().float()
        if params.dim() == 1:
            params = params.unsqueeze(0)
        if params.shape[1] != self.population_actor.num_parameters:
            raise ValueError(f"expected {self.population_actor.num_parameters} parameters per member, got {params.shape[1]}")
        if seeds is None:
            seeds = self.seeds.integers(0, 2**31 - 1, size=params.shape[0]).tolist()
        generation = self.backend.rollout(params.contiguous(), seeds)
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


def default_backend(env_id: str) -> str:
    """The fastest backend that supports ``env_id``."""
    for name, backend in BACKENDS.items():
        supports = getattr(backend, "supports", None)
        if name != "gym" and supports is not None and supports(env_id):
            return name
    return "gym"


# Fast backends register themselves in BACKENDS; imported last because they use the names above.
from torchrl_esrl import mujoco_batch as _mujoco_batch  # noqa: E402,F401
