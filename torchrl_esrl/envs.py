"""Environments (paper, Section 4.1): gymnasium v5 MuJoCo tasks seen through TorchRL.

One :class:`EnvSpec` (the config's ``env`` section: id, gymnasium keyword arguments, gymnasium
wrappers, TorchRL transforms, time limit) describes the task for every part of a run: TD3 acts
in :meth:`EnvSpec.make_torchrl` (float32 observations, episode return and step count, then the
user's transforms); ES offspring and every evaluation play :meth:`EnvSpec.make_gym` (the same
gymnasium env and wrappers) through the backends of :mod:`torchrl_esrl.collectors.es_collector`,
or the TorchRL env itself where the spec has transforms; the networks and buffers are sized by
:meth:`EnvSpec.sizes`, once the env has been made, reset and stepped (before a run, in a child
process: :meth:`EnvSpec.checked_sizes`), so that a value that fails only when the env is played
is refused in one line naming its key. Names resolve with :func:`resolve_env_id`.
"""
from __future__ import annotations

import difflib
import inspect
import logging
import sys
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
import torch
from torchrl_esrl.env_play import NotPlayable, in_child, play_gym, play_torchrl, same_state
from torchrl_esrl.errors import ConfigError, error_line
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

    def __post_init__(self) -> None:
        """The time limit given as a keyword argument too (``env.kwargs.max_episode_steps``, which
        ``gymnasium.make`` takes) is one value: ``max_episode_steps``; given twice with two values,
        a :class:`ConfigError` naming both keys."""
        if "max_episode_steps" not in self.kwargs:
            return
        kwargs = dict(self.kwargs)
        value = kwargs.pop("max_episode_steps")
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value <= 0):
            raise ConfigError(f"env.kwargs.max_episode_steps: {value!r} is invalid (allowed: a positive integer, best given as env.max_episode_steps)")
        if value is not None and self.max_episode_steps is not None and int(self.max_episode_steps) != value:
            raise ConfigError(
                f"env.kwargs.max_episode_steps: {value} and env.max_episode_steps: {self.max_episode_steps} both set the time limit "
                f"(allowed: one of them, e.g. env.max_episode_steps={value}, or equal values)"
            )
        object.__setattr__(self, "kwargs", kwargs)
        if value is not None:
            object.__setattr__(self, "max_episode_steps", value)

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
        included), once it has been played (:func:`~torchrl_esrl.env_play.play_gym`, and through TorchRL where the spec has
        transforms); :class:`ConfigError` naming the key where the algorithms cannot take it or it
        cannot be played (:meth:`_refusal`)."""
        quiet_logs()
        try:
            env = self.make_gym()
        except ConfigError:
            raise
        except Exception as error:  # noqa: BLE001 - a keyword or wrapper that fails when made, a missing package or asset
            raise self._refusal(NotPlayable("made", "fails", error_line(error))) from None
        try:
            observation, action, limit = env.observation_space, env.action_space, env.spec.max_episode_steps if env.spec else None
            field_name = "env.wrappers" if self.wrappers else "env.id"
            if not isinstance(action, gym.spaces.Box) or len(action.shape) != 1 or not (np.isfinite(action.low).all() and np.isfinite(action.high).all()):
                raise ConfigError(f"{field_name}: '{self.id}' has the action space {action} (allowed: {TASKS_ALLOWED})")
            if not isinstance(observation, gym.spaces.Box) or len(observation.shape) != 1:
                raise ConfigError(f"{field_name}: '{self.id}' has the observation space {observation} (allowed: {TASKS_ALLOWED})")
            try:
                before, after = play_gym(env, len(self.wrappers))
            except NotPlayable as failure:
                raise self._refusal(failure) from None
            changed = [key for key in before if before[key] != after.get(key)]
            if changed:  # the same reset after a few steps must find every wrapper as the first reset left it
                raise ConfigError(f"env.wrappers: {changed[0]} keeps state from one episode to the next (running statistics), which TD3's env, every ES offspring and every evaluation would each keep apart (allowed: wrappers whose state an episode's reset restores)")
        finally:
            env.close()
        steps = int(self.max_episode_steps) if self.max_episode_steps is not None else limit
        observation_dim = int(observation.shape[0])
        if self.transforms:
            observation_dim = self._check_transforms()
        return EnvSizes(observation_dim, int(action.shape[0]), None if steps is None else int(steps))

    def _check_transforms(self) -> int:
        """The observation size after the user's transforms, once the TorchRL env has been played
        (:func:`~torchrl_esrl.env_play.play_torchrl`); :class:`ConfigError` for a transform that keeps state from one
        episode to the next (running statistics): TD3's env, every ES offspring and every
        evaluation would each keep a state of their own."""
        try:
            env, spec = self._made_torchrl()
        except NotPlayable as failure:
            raise self._refusal(failure) from None
        try:
            if spec is None or len(spec.shape) != 1:
                raise ConfigError(f"env.transforms: the observation becomes {spec} (allowed: transforms that keep a flat 'observation')")
            try:
                before, after = play_torchrl(env)
            except NotPlayable as failure:
                raise self._refusal(failure) from None
            changed = [key for key, value in after.items() if not same_state(before.get(key), value)]
            if changed:
                raise ConfigError(f"env.transforms: a transform keeps state from one episode to the next ({changed[0]}: running statistics), which TD3's env, every ES offspring and every evaluation would each keep apart (allowed: transforms whose state an episode's reset restores)")
            return int(spec.shape[0])
        finally:
            env.close()

    def _made_torchrl(self) -> tuple[TransformedEnv, Any]:
        """:meth:`make_torchrl` (seed 0) and its observation's spec, which TorchRL computes through
        the transforms when first read; :class:`NotPlayable` where either raises."""
        try:
            env = self.make_torchrl(seed=0)
        except ConfigError:
            raise
        except Exception as error:  # noqa: BLE001 - a transform whose arguments fail with this env
            raise NotPlayable("made", "fails", error_line(error)) from None
        try:
            return env, env.observation_spec.get("observation", None)
        except Exception as error:  # noqa: BLE001
            env.close()
            raise NotPlayable("made", "fails", error_line(error)) from None

    def play_failure(self) -> "NotPlayable | None":
        """How this spec fails when it is made and played (:func:`~torchrl_esrl.env_play.play_gym`, then through TorchRL
        where it has transforms), or None where it plays."""
        quiet_logs()
        try:
            env = self.make_gym()
        except Exception as error:  # noqa: BLE001 - whatever making it raises is how it fails
            return NotPlayable("made", "fails", error_line(error))
        try:
            play_gym(env)
        except NotPlayable as failure:
            return failure
        finally:
            env.close()
        if not self.transforms:
            return None
        try:
            env = self._made_torchrl()[0]
        except NotPlayable as failure:
            return failure
        try:
            play_torchrl(env)
        except NotPlayable as failure:
            return failure
        finally:
            env.close()
        return None

    def parts(self) -> list[tuple[str, str, "EnvSpec"]]:
        """The spec built up one entry at a time, from the registered task alone to this spec:
        ``(key, the entry in words, the spec up to that entry)`` for ``env.id``, each keyword
        argument, each wrapper, each transform, in order."""
        parts = [("env.id", repr(self.id), EnvSpec(self.id, max_episode_steps=self.max_episode_steps))]
        for count, (key, value) in enumerate(self.kwargs.items(), 1):
            parts.append((f"env.kwargs.{key}", repr(value), replace(self, kwargs=dict(list(self.kwargs.items())[:count]), wrappers=(), transforms=())))
        for index, entry in enumerate(self.wrappers):
            parts.append((f"env.wrappers[{index}]", _target_name(entry), replace(self, wrappers=self.wrappers[: index + 1], transforms=())))
        for index, entry in enumerate(self.transforms):
            parts.append((f"env.transforms[{index}]", _target_name(entry), replace(self, transforms=self.transforms[: index + 1])))
        return parts

    def _refusal(self, failure: "NotPlayable") -> ConfigError:
        """The one line of a spec that fails when played: the first entry whose addition makes the
        env fail (:meth:`parts`, each played alone up to it), and how it fails."""
        parts = self.parts()
        for key, entry, spec in parts[:-1]:
            found = spec.play_failure()
            if found is not None:
                return _refused(self.id, key, entry, found)
        key, entry, _ = parts[-1]
        return _refused(self.id, key, entry, failure)

    def checked_sizes(self) -> EnvSizes:
        """:meth:`sizes`, computed in a child process (forked where the platform can, so that it
        costs the env's making and play, not a new interpreter): an env that ends its process (a
        native crash in the simulator, a wrapper or a transform) ends the child, and is refused in
        one line naming the first entry (:meth:`parts`) whose play ends a process too. The child's
        own output (warnings of a failing env) is not shown."""
        kind, value = in_child(EnvSpec.sizes, self)
        if kind == "returned":
            return value
        if kind == "refused":
            raise ConfigError(value)
        for key, entry, spec in self.parts():
            found = in_child(EnvSpec.play_failure, spec)[1]  # None where it plays, else how it fails or ends
            if found is not None:
                raise _refused(self.id, key, entry, found)
        key, entry, _ = self.parts()[-1]  # every part plays: sizes() alone ends the process
        raise _refused(self.id, key, entry, value)


ALLOWED_PLAY = "values with which {id} resets and steps, its observations and rewards finite"


def _refused(env_id: str, key: str, entry: str, failure: NotPlayable) -> ConfigError:
    """The one line of the key ``key`` (its value or entry in words, ``entry``) whose env fails when played."""
    where = f" when {env_id} is made" if failure.where == "made" else f" at {env_id}'s {failure.where}" if failure.where else f" {env_id}"
    allowed = TASKS_ALLOWED if key == "env.id" else ALLOWED_PLAY.format(id=env_id)
    detail = f" ({failure.detail})" if failure.detail else ""
    return ConfigError(f"{key}: {entry} {failure.what}{where}{detail} (allowed: {allowed})")


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
    buffers = tuple(sorted((name, _buffer_value(buffer)) for name, buffer in transform.named_buffers()))
    return (f"{type(transform).__module__}.{type(transform).__qualname__}", settings, buffers)


def _buffer_value(buffer: torch.Tensor) -> tuple:
    """A transform's buffer in its description: its values (its shape where large), or that it
    is not made yet (a lazy buffer a transform fills at the first reset, as ``CatFrames``'s)."""
    if isinstance(buffer, torch.nn.parameter.UninitializedTensorMixin):
        return ("uninitialized",)
    return tuple(buffer.flatten().tolist()) if buffer.numel() <= 1024 else ("tensor", tuple(buffer.shape))


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
