"""Playing an env before a run (:meth:`torchrl_esrl.envs.EnvSpec.checked_sizes`): reset, a few
random steps, reset again, through gymnasium and through TorchRL, in a child process, so that a
value of the config that fails only when the env is played (a keyword, a wrapper, a transform, a
native crash, a non-finite observation, an unstable simulation) is found before any work starts,
and a wrapper or transform that keeps state across resets is found by comparing its state.
"""
from __future__ import annotations

import os
import signal
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from torchrl_esrl.errors import ConfigError, error_line

PLAY_STEPS = 3  # steps of the play before a run: the wrappers' and transforms' state checks compare the resets around them
UNSTABLE = ("BADQPOS", "BADQVEL", "BADQACC")  # MuJoCo's warnings that its simulation is unstable (it resets the state)
class NotPlayable(Exception):
    """How an env fails when played: ``where`` (``made``, ``reset``, ``step 1``...; empty where not
    known), ``what`` it does (``fails``, ``gives a non-finite reward (nan)``) and ``detail`` (the
    exception raised)."""

    def __init__(self, where: str, what: str, detail: str = ""):
        super().__init__(where, what, detail)
        self.where, self.what, self.detail = where, what, detail


def _check_played(where: str, env, **values) -> None:
    """:class:`NotPlayable` where one of ``values`` (an observation, a reward) is not finite, or
    where MuJoCo has warned that the simulation of ``env`` is unstable."""
    for name, value in values.items():
        array = np.asarray(value, dtype=np.float64)
        if not np.isfinite(array).all():
            raise NotPlayable(where, f"gives a non-finite {name} ({array[~np.isfinite(array)].flat[0]})")
    data = getattr(getattr(env, "unwrapped", env), "data", None)
    if data is not None and hasattr(data, "warning"):
        import mujoco

        for name in UNSTABLE:
            if data.warning[getattr(mujoco.mjtWarning, f"mjWARN_{name}")].number:
                raise NotPlayable(where, f"makes MuJoCo's simulation unstable (its warning: NaN, Inf or huge value in {name[3:].lower()})")


def play_gym(env: gym.Env, layers: int = 0) -> tuple[dict, dict]:
    """Plays a gymnasium env as a run would: reset (seed 0), :data:`PLAY_STEPS` steps of uniform
    random actions (fewer if the episode ends), reset again (seed 0). :class:`NotPlayable` where a
    call raises, an observation or a reward is not finite, or MuJoCo finds its simulation
    unstable. Returns the state of the outer ``layers`` wrappers after each reset."""
    where = "reset"
    try:
        observation, _ = env.reset(seed=0)
        _check_played(where, env, observation=observation)
        before = _wrapper_state(env, layers)
        rng, space = np.random.default_rng(0), env.action_space
        box = isinstance(space, gym.spaces.Box)
        low, high = (np.where(np.isfinite(space.low), space.low, -1.0), np.where(np.isfinite(space.high), space.high, 1.0)) if box else (None, None)
        for step in range(1, PLAY_STEPS + 1):
            where = f"step {step}"
            action = rng.uniform(low, high).astype(space.dtype) if box else space.sample()
            observation, reward, terminated, truncated, _ = env.step(action)
            _check_played(where, env, observation=observation, reward=reward)
            if terminated or truncated:
                break
        where = "second reset"
        observation, _ = env.reset(seed=0)
        _check_played(where, env, observation=observation)
        return before, _wrapper_state(env, layers)
    except NotPlayable:
        raise
    except Exception as error:  # noqa: BLE001 - whatever the env raises is how it fails
        raise NotPlayable(where, "fails", error_line(error)) from None


def play_torchrl(env) -> tuple[dict, dict]:
    """Plays a TorchRL env (the user's transforms included): reset (seed 0), a rollout of
    :data:`PLAY_STEPS` random steps, reset again (seed 0); :class:`NotPlayable` as
    :func:`play_gym`. Returns the transforms' state after each reset."""
    where = "reset"
    try:
        env.set_seed(0)
        reset = env.reset()
        _check_played(where, None, observation=reset["observation"])
        before = _transform_state(env.transform)
        where = f"first {PLAY_STEPS} steps"
        rollout = env.rollout(PLAY_STEPS, break_when_any_done=False)
        _check_played(where, None, observation=rollout["next", "observation"], reward=rollout["next", "reward"])
        where = "second reset"
        env.set_seed(0)
        _check_played(where, None, observation=env.reset()["observation"])
        return before, _transform_state(env.transform)
    except NotPlayable:
        raise
    except Exception as error:  # noqa: BLE001
        raise NotPlayable(where, "fails", error_line(error)) from None


def in_child(function, *args) -> tuple[str, Any]:
    """``function(*args)`` in a child process: ``("returned", its value)``, ``("refused", the
    line of the ConfigError it raised)``, or ``("ended", NotPlayable)`` where the child ended
    without a word (a native crash: the signal, and the first line the child printed)."""
    import multiprocessing
    import tempfile

    context = multiprocessing.get_context("fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn")
    receiver, sender = context.Pipe(duplex=False)
    with tempfile.NamedTemporaryFile(prefix="torchrl_esrl-env-") as output:
        process = context.Process(target=_child, args=(sender, output.name, function, args), daemon=True)
        process.start()
        sender.close()
        try:
            kind, value = receiver.recv()
        except EOFError:
            kind, value = "ended", None
        process.join()
        receiver.close()
        if kind == "failed":  # not a config error: the check itself failed
            raise RuntimeError(f"the env check failed in its child process:\n{value}")
        if kind == "ended":
            code = process.exitcode
            how = f"signal {signal.Signals(-code).name if -code in signal.valid_signals() else -code}" if code is not None and code < 0 else f"exit code {code}"
            printed = next((line.strip() for line in Path(output.name).read_text(errors="replace").splitlines() if line.strip()), "")
            value = NotPlayable("", "ends the process that plays", f"{how}: {printed}"[:300] if printed else how)
    return kind, value


def _child(sender, output: str, function, args) -> None:
    """The child of :func:`in_child`: its output to ``output``, its outcome to ``sender``."""
    import faulthandler
    import traceback

    fd = os.open(output, os.O_WRONLY | os.O_APPEND)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    faulthandler.enable(file=2)  # a native crash's first line: what the parent's one line says
    warnings.simplefilter("ignore")
    try:
        outcome = ("returned", function(*args))
    except ConfigError as error:
        outcome = ("refused", str(error))
    except Exception:  # noqa: BLE001 - sent to the parent, which raises it
        outcome = ("failed", traceback.format_exc())
    sender.send(outcome)
    sender.close()


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


def same_state(a, b) -> bool:
    return (a is None and b is None) or (a is not None and b is not None and a.shape == b.shape and torch.equal(a, b))
