"""Environments (paper, Section 4.1): gymnasium v5 MuJoCo tasks seen through TorchRL.

One :class:`EnvSpec` (the config's ``env`` section: id, gymnasium keyword arguments, gymnasium
wrappers, TorchRL transforms, time limit) describes the task for every part of a run: TD3 acts
in :meth:`EnvSpec.make_torchrl` (float32 observations, episode return and step count, then the
user's transforms); ES offspring and every evaluation play :meth:`EnvSpec.make_gym` (the same
gymnasium env and wrappers) through the backends of :mod:`torchrl_esrl.collectors.es_collector`,
or the TorchRL env itself where the spec has transforms; the networks and buffers are sized by
:meth:`EnvSpec.sizes`. Names resolve with :func:`resolve_env_id`.
"""
from __future__ import annotations

import difflib
import inspect
import logging
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
import torch
from torchrl_esrl.errors import ConfigError
from torchrl.envs import Compose, DoubleToFloat, GymEnv, GymWrapper, RewardSum, StepCounter, TransformedEnv

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


def env_sizes(env: "str | EnvSpec", max_episode_steps: int | None = None) -> EnvSizes:
    """Sizes of the task (an id, or an :class:`EnvSpec` with its keyword arguments and wrappers),
    made once with gymnasium; :class:`ConfigError` naming the field if the algorithms cannot take
    it (the actor's tanh output needs a bounded continuous Box action space, the MLPs a flat Box
    observation space)."""
    return as_env_spec(env, max_episode_steps).sizes()


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


def _target_name(entry) -> str:
    return str(entry.get("_target_", "?")) if isinstance(entry, Mapping) else repr(entry)


def _instantiate(field_name: str, entry, *args):
    """``hydra.utils.instantiate(entry, *args)``, with a one-line :class:`ConfigError` naming the
    field and the entry where it cannot be made."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    if not isinstance(entry, Mapping) or "_target_" not in entry:
        raise ConfigError(f"{field_name}: {entry!r} is invalid (allowed: a mapping with a _target_, e.g. {{_target_: gymnasium.wrappers.ClipReward, min_reward: -1, max_reward: 1}})")
    try:
        return instantiate(entry, *args, _convert_="all")
    except InstantiationException as error:
        cause = error.__cause__ or error
        text = str(cause).strip().splitlines()[0] if str(cause).strip() else type(cause).__name__
        raise ConfigError(f"{field_name}: {_target_name(entry)} cannot be made ({text})") from None


TD3_TRANSFORMS = (DoubleToFloat, RewardSum, StepCounter)  # the project's own transforms of the TorchRL env, in order


def project_transforms(user_transforms: Sequence = ()) -> Compose:
    """The transforms of every TorchRL env of the project: float32 observations, the user's
    transforms, ``episode_reward``, ``step_count``."""
    first, *counters = (transform() for transform in TD3_TRANSFORMS)
    return Compose(first, *user_transforms, *counters)


@dataclass(frozen=True)
class EnvSpec:
    """The task as every part of a run plays it: ``gymnasium.make(id, **kwargs)`` (with
    ``max_episode_steps``), then ``wrappers`` in order (Hydra ``_target_`` configs, each called
    with the env as its first argument), and in TorchRL ``DoubleToFloat``, then ``transforms``
    (``_target_`` configs of TorchRL transforms), then ``RewardSum`` and ``StepCounter``: the
    return is the sum of the rewards TD3 learns from, in TD3's env as in every ES episode.

    It is the description each fast piece reads to decide whether it computes exactly what its
    reference would (:mod:`torchrl_esrl.run.implementation`)."""

    id: str
    kwargs: Mapping[str, Any] = field(default_factory=dict)
    wrappers: Sequence[Mapping[str, Any]] = ()
    transforms: Sequence[Mapping[str, Any]] = ()
    max_episode_steps: int | None = None

    @classmethod
    def from_config(cls, env_cfg) -> "EnvSpec":
        """The spec of a config's ``env`` section (``conf/env/*.yaml``)."""
        from omegaconf import OmegaConf

        def plain(node, default):
            if node is None:
                return default
            return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node

        steps = env_cfg.get("max_episode_steps")
        return cls(
            resolve_env_id(env_cfg.id),
            dict(plain(env_cfg.get("kwargs"), {})),
            tuple(plain(env_cfg.get("wrappers"), [])),
            tuple(plain(env_cfg.get("transforms"), [])),
            None if steps is None else int(steps),
        )

    @property
    def plain(self) -> bool:
        """The registered task as gymnasium defines it: no keyword arguments, wrappers or transforms."""
        return not (self.kwargs or self.wrappers or self.transforms)

    def changes(self) -> list[str]:
        """What the spec changes from the registered task, one short entry each
        (``env.kwargs.main_body=4``, ``env.wrappers: ClipReward``)."""
        return (
            [f"env.kwargs.{key}={value!r}" for key, value in self.kwargs.items()]
            + [f"env.wrappers: {_target_name(w).rpartition('.')[2]}" for w in self.wrappers]
            + [f"env.transforms: {_target_name(t).rpartition('.')[2]}" for t in self.transforms]
        )

    def make_gym(self, wrappers: bool = True) -> gym.Env:
        """``gymnasium.make`` with the keyword arguments, then the wrappers (unless ``wrappers`` is False)."""
        kwargs = dict(self.kwargs)
        if self.max_episode_steps is not None:
            kwargs["max_episode_steps"] = int(self.max_episode_steps)
        try:
            env = gym.make(self.id, **kwargs)
        except TypeError as error:
            allowed = ", ".join(constructor_keywords(self.id)) or "none"
            raise ConfigError(f"env.kwargs: {self.id} cannot take {sorted(self.kwargs)} ({str(error).strip().splitlines()[0]}; allowed: {allowed})") from None
        for index, entry in enumerate(self.wrappers if wrappers else ()):
            env = _instantiate(f"env.wrappers[{index}]", entry, env)
            if not isinstance(env, gym.Env):
                raise ConfigError(f"env.wrappers[{index}]: {_target_name(entry)} made a {type(env).__name__} (allowed: a gymnasium wrapper)")
        return env

    def make_transforms(self) -> list:
        """The user's TorchRL transforms, made from their configs."""
        return [_instantiate(f"env.transforms[{index}]", entry) for index, entry in enumerate(self.transforms)]

    def make_torchrl(self, seed: int | None = None) -> TransformedEnv:
        """The TorchRL env: the gymnasium env (``GymEnv`` for the registered task, ``GymWrapper``
        around :meth:`make_gym` otherwise) and :func:`project_transforms` with the user's."""
        if self.kwargs or self.wrappers:
            base = GymWrapper(self.make_gym())
        else:
            steps = {} if self.max_episode_steps is None else {"max_episode_steps": int(self.max_episode_steps)}
            base = GymEnv(self.id, **steps)
        env = TransformedEnv(base, project_transforms(self.make_transforms()))
        if seed is not None:
            env.set_seed(seed)
        return env

    def sizes(self) -> EnvSizes:
        """What the networks and buffers are sized by, read off the env every part plays (wrappers
        included); :class:`ConfigError` where the algorithms cannot take it."""
        quiet_logs()
        try:
            env = self.make_gym()
        except ConfigError:
            raise
        except Exception as error:  # noqa: BLE001 - a registered id whose package or assets are missing
            text = str(error).strip().splitlines()[0] if str(error).strip() else ""
            raise ConfigError(f"env.id: '{self.id}' cannot be made ({type(error).__name__}: {text}) (allowed: {TASKS_ALLOWED})") from None
        try:
            observation, action, limit = env.observation_space, env.action_space, env.spec.max_episode_steps if env.spec else None
            field_name = "env.wrappers" if self.wrappers else "env.id"
            if not isinstance(action, gym.spaces.Box) or len(action.shape) != 1 or not (np.isfinite(action.low).all() and np.isfinite(action.high).all()):
                raise ConfigError(f"{field_name}: '{self.id}' has the action space {action} (allowed: {TASKS_ALLOWED})")
            if not isinstance(observation, gym.spaces.Box) or len(observation.shape) != 1:
                raise ConfigError(f"{field_name}: '{self.id}' has the observation space {observation} (allowed: {TASKS_ALLOWED})")
            if self.wrappers:
                self._check_wrappers(env)
        finally:
            env.close()
        steps = int(self.max_episode_steps) if self.max_episode_steps is not None else limit
        observation_dim = int(observation.shape[0])
        if self.transforms:
            observation_dim = self._check_transforms()
        return EnvSizes(observation_dim, int(action.shape[0]), None if steps is None else int(steps))

    def _check_transforms(self) -> int:
        """The observation size after the user's transforms; :class:`ConfigError` for a transform
        that keeps state from one episode to the next (running statistics): TD3's env, every ES
        offspring and every evaluation would each keep a state of their own."""
        env = self.make_torchrl(seed=0)
        try:
            spec = env.observation_spec.get("observation", None)
            if spec is None or len(spec.shape) != 1:
                raise ConfigError(f"env.transforms: the observation becomes {spec} (allowed: transforms that keep a flat 'observation')")
            env.set_seed(0)
            env.reset()
            before = _transform_state(env.transform)
            env.rollout(3, break_when_any_done=False)
            env.set_seed(0)
            env.reset()
            changed = [key for key, value in _transform_state(env.transform).items() if not _same(before.get(key), value)]
            if changed:
                raise ConfigError(f"env.transforms: a transform keeps state from one episode to the next ({changed[0]}: running statistics), which TD3's env, every ES offspring and every evaluation would each keep apart (allowed: transforms whose state an episode's reset restores)")
            return int(spec.shape[0])
        finally:
            env.close()

    def _check_wrappers(self, env: gym.Env) -> None:
        """:class:`ConfigError` for a wrapper that keeps state from one episode to the next (running
        statistics, as ``NormalizeObservation``): the same reset after a few steps must find every
        wrapper as the first reset left it."""
        env.reset(seed=0)
        before = _wrapper_state(env, len(self.wrappers))
        rng, space = np.random.default_rng(0), env.action_space
        for _ in range(3):
            env.step(rng.uniform(space.low, space.high).astype(space.dtype))
        env.reset(seed=0)
        after = _wrapper_state(env, len(self.wrappers))
        changed = [key for key in before if before[key] != after.get(key)]
        if changed:
            raise ConfigError(f"env.wrappers: {changed[0]} keeps state from one episode to the next (running statistics), which TD3's env, every ES offspring and every evaluation would each keep apart (allowed: wrappers whose state an episode's reset restores)")


def _wrapper_state(env, layers: int) -> dict:
    """The attributes of the outer ``layers`` wrappers (the user's), but the env each wraps and what
    cannot be pickled (functions), pickled, by ``Wrapper.attribute``."""
    import pickle

    state, layer = {}, env
    for _ in range(layers):
        for key, value in vars(layer).items():
            if key == "env":
                continue
            try:
                state[f"{type(layer).__name__}.{key}"] = pickle.dumps(value)
            except Exception:  # noqa: BLE001 - lambdas, locks: no state a step changes
                pass
        layer = layer.env
    return state


def _plain_value(value):
    """``value`` if it is made of strings, numbers, booleans and None (lists and tuples of them too), else ``...``."""
    if value is None or isinstance(value, (str, int, float, bool)):
        return value
    if isinstance(value, (list, tuple)):
        items = tuple(_plain_value(v) for v in value)
        return ... if ... in items else items
    return ...


def describe_transform(transform) -> tuple:
    """A transform as what it computes: its class, its settings (its keys and every public
    attribute that is a plain value: limits, flags) and its buffers' values, recursively for a
    ``Compose``. Two
    transforms with equal descriptions transform alike; a fast piece compares descriptions,
    never types alone."""
    children = getattr(transform, "transforms", None)
    if children is not None and type(transform).__name__ == "Compose":
        return ("Compose", tuple(describe_transform(child) for child in children))
    public = {k: v for k, v in vars(transform).items() if not k.startswith("_") and k != "training"}
    keys = {k: getattr(transform, k, None) for k in ("in_keys", "out_keys", "in_keys_inv", "out_keys_inv")}
    settings = tuple(sorted((key, value) for key, value in ((k, _plain_value(v)) for k, v in {**public, **keys}.items()) if value is not ...))
    buffers = tuple(sorted((name, tuple(buffer.flatten().tolist()) if buffer.numel() <= 1024 else ("tensor", tuple(buffer.shape))) for name, buffer in transform.named_buffers()))
    return (f"{type(transform).__module__}.{type(transform).__qualname__}", settings, buffers)


def _transform_state(transform) -> dict:
    """The transforms' state tensors (None where not yet made), by name."""
    state = {}

    def add(key, value):
        if isinstance(value, Mapping) or hasattr(value, "items"):  # dicts and TensorDicts of statistics
            for name, item in value.items():
                add(f"{key}.{name}", item)
        elif value is None or isinstance(value, torch.nn.parameter.UninitializedTensorMixin) or not isinstance(value, torch.Tensor):
            state[key] = None
        else:
            state[key] = value.detach().clone()

    for key, value in transform.state_dict(keep_vars=True).items():
        add(key, value)
    return state


def _same(a, b) -> bool:
    return (a is None and b is None) or (a is not None and b is not None and a.shape == b.shape and torch.equal(a, b))


def as_env_spec(env: "str | EnvSpec", max_episode_steps: int | None = None) -> EnvSpec:
    """``env`` itself if it is an :class:`EnvSpec`, else the spec of the registered task ``env``."""
    if isinstance(env, EnvSpec):
        return env
    return EnvSpec(resolve_env_id(env), max_episode_steps=None if max_episode_steps is None else int(max_episode_steps))


def constructor_keywords(env_id: str) -> list[str]:
    """The keyword arguments the registered env class of ``env_id`` takes (gymnasium.make's ``**kwargs``)."""
    from gymnasium.envs.registration import load_env_creator

    try:
        creator = load_env_creator(gym.spec(env_id).entry_point)
        return [name for name, p in inspect.signature(creator).parameters.items() if p.kind is p.KEYWORD_ONLY or p.kind is p.POSITIONAL_OR_KEYWORD]
    except Exception:  # noqa: BLE001 - an entry point that cannot be inspected: no list to offer
        return []


def make_gym_env(env: "str | EnvSpec", max_episode_steps: int | None = None) -> gym.Env:
    """The gymnasium env of ``env`` (an id or an :class:`EnvSpec`): what the ES backends play."""
    return as_env_spec(env, max_episode_steps).make_gym()


def make_env(env: "str | EnvSpec", seed: int = 0, max_episode_steps: int | None = None) -> TransformedEnv:
    """The TorchRL env TD3 interacts with (:meth:`EnvSpec.make_torchrl`), seeded."""
    return as_env_spec(env, max_episode_steps).make_torchrl(seed)


def make_train_env(cfg) -> TransformedEnv:
    """TD3's TorchRL env of a config's ``env`` section (:meth:`EnvSpec.make_torchrl`), seeded with the run's seed."""
    return EnvSpec.from_config(cfg.env).make_torchrl(seed=cfg.seed)
