"""Environments (paper, Section 4.1): gymnasium v5 MuJoCo tasks seen through TorchRL.

TD3 acts through a TorchRL :class:`~torchrl.envs.GymEnv` (float32 observations, episode
return and step count transforms); ES evaluates populations through the backends of
:mod:`torchrl_esrl.collectors.es_collector`. Both resolve names with :func:`resolve_env_id`.
"""
from __future__ import annotations

import difflib
import logging
import sys
from typing import NamedTuple

import gymnasium as gym
import numpy as np
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


TASKS_ALLOWED = "a bounded continuous Box action space and a flat Box observation space, e.g. HalfCheetah-v5 or Pendulum-v1"


class EnvSizes(NamedTuple):
    """What the networks and buffers of a task are sized by."""

    observation_dim: int
    action_dim: int
    episode_steps: int | None  # the env's time limit (None: no limit registered)


def env_sizes(env_id: str, max_episode_steps: int | None = None) -> EnvSizes:
    """Sizes of the task ``env_id``, made once with gymnasium; :class:`ConfigError` naming
    ``env.id`` if the algorithms cannot take it (the actor's tanh output needs a bounded
    continuous Box action space, the MLPs a flat Box observation space)."""
    env_id = resolve_env_id(env_id)
    quiet_logs()
    try:
        env = gym.make(env_id)
    except Exception as error:  # noqa: BLE001 - a registered id whose package or assets are missing
        raise ConfigError(f"env.id: '{env_id}' cannot be made ({type(error).__name__}: {str(error).strip().splitlines()[0] if str(error).strip() else ''}) (allowed: {TASKS_ALLOWED})") from None
    try:
        observation, action, limit = env.observation_space, env.action_space, env.spec.max_episode_steps if env.spec else None
    finally:
        env.close()
    if not isinstance(action, gym.spaces.Box) or len(action.shape) != 1 or not (np.isfinite(action.low).all() and np.isfinite(action.high).all()):
        raise ConfigError(f"env.id: '{env_id}' has the action space {action} (allowed: {TASKS_ALLOWED})")
    if not isinstance(observation, gym.spaces.Box) or len(observation.shape) != 1:
        raise ConfigError(f"env.id: '{env_id}' has the observation space {observation} (allowed: {TASKS_ALLOWED})")
    steps = int(max_episode_steps) if max_episode_steps is not None else limit
    return EnvSizes(int(observation.shape[0]), int(action.shape[0]), None if steps is None else int(steps))


# Messages that say nothing to a user of this package, silenced at their source and nowhere else:
# MuJoCo's compiler deprecation of an attribute the gymnasium v5 models use (printed by the C library,
# and appended to MUJOCO_LOG.TXT in the working directory, at every model compile), and TorchRL's
# INFO line at every replay-buffer storage allocation.
MUJOCO_SILENCED = ("compiler attribute 'settotalmass' is deprecated",)
TORCHRL_SILENCED = ("Initialized LazyTensorStorage with", "Initialized LazyMemmapStorage with")


def _mujoco_warning(message: str) -> None:
    """MuJoCo's user warning handler: the silenced messages are dropped, every other one is printed
    as MuJoCo's default handler prints it."""
    if not any(text in message for text in MUJOCO_SILENCED):
        print(f"WARNING: {message}", file=sys.stderr, flush=True)


def _torchrl_record(record: logging.LogRecord) -> bool:
    return not any(str(record.msg).startswith(text) for text in TORCHRL_SILENCED)


def quiet_logs() -> None:
    """Keep the console for the progress bar (called once at start-up by every recipe, through
    :class:`~torchrl_esrl.run.harness.RunHarness`): drop exactly the messages listed above."""
    import mujoco

    mujoco.set_mju_user_warning(_mujoco_warning)
    torchrl_logger = logging.getLogger("torchrl")
    if _torchrl_record not in torchrl_logger.filters:
        torchrl_logger.addFilter(_torchrl_record)


def make_gym_env(env_id: str, max_episode_steps: int | None = None) -> gym.Env:
    """A plain gymnasium env (the reference the fast ES backend is checked against)."""
    kwargs = {} if max_episode_steps is None else {"max_episode_steps": int(max_episode_steps)}
    return gym.make(resolve_env_id(env_id), **kwargs)


TD3_TRANSFORMS = (DoubleToFloat, RewardSum, StepCounter)  # the transforms of make_env, in order


def make_env(env_id: str, seed: int = 0, max_episode_steps: int | None = None) -> TransformedEnv:
    """The TorchRL env TD3 interacts with: float32 observations, ``episode_reward``, ``step_count``."""
    kwargs = {} if max_episode_steps is None else {"max_episode_steps": int(max_episode_steps)}
    env = TransformedEnv(
        GymEnv(resolve_env_id(env_id), **kwargs),
        Compose(*(transform() for transform in TD3_TRANSFORMS)),
    )
    env.set_seed(seed)
    return env
