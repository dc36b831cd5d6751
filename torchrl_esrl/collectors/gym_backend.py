"""The reference ES backend: one env per member, stepped in lock-step with one batched policy
forward per step. Any gymnasium id works; the fast backends are checked against it.

Each member plays the run's :class:`~torchrl_esrl.envs.EnvSpec`: its gymnasium env (keyword
arguments and wrappers) or, where the spec has TorchRL transforms, the TorchRL env TD3 plays
(transforms included), so that what the policy sees and what a return is are the same in TD3, ES
and evaluation."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from torchrl_esrl.collectors.generation import Generation, transitions_from_arrays
from torchrl_esrl.envs import EnvSpec, as_env_spec
from torchrl.envs.utils import step_mdp

from torchrl_esrl.modules.population import Mirrored, PopulationActor, one_blas_thread
from torchrl_esrl.torchrl_private import gym_env_of


class GymBackend:
    """Reference backend: P gymnasium envs stepped in lock-step, one batched forward per step."""

    name = "gym"

    def __init__(self, env: "str | EnvSpec", population_actor: PopulationActor, max_episode_steps: int | None = None):
        self.spec = as_env_spec(env, max_episode_steps)
        self.env_id = self.spec.id
        self.policy = population_actor
        self.envs: list = []
        probe = self._env(0)
        self.horizon = int(probe.spec.max_episode_steps or 1000)
        self.observation_dim = int(np.prod(probe.observation_space.shape))
        self.action_dim = int(np.prod(probe.action_space.shape))

    @staticmethod
    def refusal(env) -> None:
        """The reference plays every spec."""
        return None

    def _env(self, i: int):
        while len(self.envs) <= i:
            self.envs.append(TorchRLMember(self.spec) if self.spec.transforms else self.spec.make_gym())
        return self.envs[i]

    def rollout(self, params: torch.Tensor, seeds: Sequence[int], mirrored: Mirrored | None = None) -> Generation:
        """One episode per row of ``params``; given ``mirrored`` (the same population as pairs),
        the actions come from :meth:`PopulationActor.mirrored`, as the fast backends compute them."""
        with one_blas_thread():
            return self._rollout(params, seeds, mirrored)

    def _rollout(self, params: torch.Tensor, seeds: Sequence[int], mirrored: Mirrored | None) -> Generation:
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
        if mirrored is None:
            layers = self.policy.split(params)
        else:
            center, offsets = self.policy.split_pairs(mirrored)
        t = 0
        while active.any():
            # Finished members still get a (cheap) forward: slicing params would copy P x D floats.
            if mirrored is None:
                action = self.policy(params, torch.as_tensor(current, dtype=torch.float32), layers).numpy()
            else:
                action = self.policy.mirrored(center, offsets, current.astype(np.float32).reshape(2, population // 2, -1)).reshape(population, -1)
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


class TorchRLMember:
    """One member's TorchRL env (:meth:`EnvSpec.make_torchrl`, the user's transforms included),
    played through gymnasium's ``reset(seed)``/``step(action)`` calls: ``set_seed(seed)`` then
    ``reset()`` starts an episode, and observations, rewards and flags are the transformed ones."""

    def __init__(self, spec: EnvSpec):
        import gymnasium as gym

        self.env = spec.make_torchrl()
        self.td = None
        self.spec = gym_env_of(self.env).spec  # the time limit (horizon) of the gymnasium env inside
        observation = self.env.observation_spec["observation"]
        action = self.env.action_spec
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, tuple(observation.shape), np.float32)
        self.action_space = gym.spaces.Box(action.space.low.numpy(), action.space.high.numpy(), dtype=np.float32)

    def reset(self, seed: int | None = None):
        if seed is not None:
            self.env.set_seed(int(seed))
        self.td = self.env.reset()
        return self.td["observation"].numpy(), {}

    def step(self, action):
        self.td.set("action", torch.as_tensor(action, dtype=self.env.action_spec.dtype))
        out = self.env.step(self.td)
        nxt = out["next"]
        self.td = step_mdp(out)
        return nxt["observation"].numpy(), float(nxt["reward"].item()), bool(nxt["terminated"].item()), bool(nxt["truncated"].item()), {}
