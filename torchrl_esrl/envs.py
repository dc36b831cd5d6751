"""Environments (paper, Section 4.1): gymnasium v5 MuJoCo tasks seen through TorchRL.

TD3 acts through a TorchRL :class:`~torchrl.envs.GymEnv` (float32 observations, episode
return and step count transforms); ES evaluates populations through the backends of
:mod:`torchrl_esrl.collectors.es_collector`. Both resolve names with :func:`resolve_env_id`.
"""
from __future__ import annotations

import difflib
import logging

import gymnasium as gym
from torchrl_esrl.errors import ConfigError
from torchrl.envs import Compose, DoubleToFloat, GymEnv, RewardSum, StepCounter, TransformedEnv

# Short names used by the Hydra config group ``env``.
ENV_IDS = {
    "halfcheetah": "HalfCheetah-v5",
    "ant": "Ant-v5",
    "swimmer": "Swimmer-v5",
    "walker2d": "Walker2d-v5",
    "hopper": "Hopper-v5",
    "inverted_pendulum": "InvertedPendulum-v5",
    "pendulum": "Pendulum-v1",
}


def resolve_env_id(name: str) -> str:
    """Map a short name or any registered gymnasium id to a gymnasium id, or raise ConfigError."""
    if name in ENV_IDS:
        return ENV_IDS[name]
    if name in gym.registry:
        return name
    known = sorted(ENV_IDS) + sorted(ENV_IDS.values())
    close = difflib.get_close_matches(name, known + list(gym.registry), n=1)
    hint = f"; did you mean '{close[0]}'?" if close else ""
    raise ConfigError(f"env.id: unknown environment '{name}'{hint} (allowed: {', '.join(known)} or any gymnasium id)")


def quiet_logs() -> None:
    """Keep the console for the progress bar: TorchRL's storage INFO lines go to WARNING level."""
    logging.getLogger("torchrl").setLevel(logging.WARNING)


def make_gym_env(env_id: str, max_episode_steps: int | None = None) -> gym.Env:
    """A plain gymnasium env (the reference the fast ES backend is checked against)."""
    kwargs = {} if max_episode_steps is None else {"max_episode_steps": int(max_episode_steps)}
    return gym.make(resolve_env_id(env_id), **kwargs)


def make_env(env_id: str, seed: int = 0, max_episode_steps: int | None = None) -> TransformedEnv:
    """The TorchRL env TD3 interacts with: float32 observations, ``episode_reward``, ``step_count``."""
    kwargs = {} if max_episode_steps is None else {"max_episode_steps": int(max_episode_steps)}
    env = TransformedEnv(
        GymEnv(resolve_env_id(env_id), **kwargs),
        Compose(DoubleToFloat(), RewardSum(), StepCounter()),
    )
    env.set_seed(seed)
    return env
