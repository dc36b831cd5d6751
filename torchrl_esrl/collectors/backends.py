"""The one registry of ES population backends (``es.backend``).

Each entry names where its class lives; it is imported on first use, so optional dependencies
(Ray) load only when asked for and no backend module imports another.
"""
from __future__ import annotations

import importlib
from collections.abc import Callable, Collection

from omegaconf import OmegaConf

from torchrl_esrl.envs import EnvSpec
from torchrl_esrl.errors import ConfigError
from torchrl_esrl.run.implementation import chosen_pieces
from torchrl_esrl.threads import job_cores

BACKENDS: dict[str, str] = {
    "gym": "torchrl_esrl.collectors.gym_backend:GymBackend",  # the reference, any gymnasium id
    "mujoco_batch": "torchrl_esrl.collectors.mujoco_batch:MujocoBatchBackend",  # gymnasium v5 MuJoCo tasks
    "ray": "torchrl_esrl.collectors.ray_backend:make_ray_backend",  # offspring on Ray workers
}
LOCAL_BACKENDS = ("gym", "mujoco_batch")  # what a Ray worker may run


def available_backends() -> list[str]:
    return ["auto", *BACKENDS]


def backend_class(name: str) -> Callable[..., object]:
    """The class (or factory) registered under ``name``."""
    module, _, attribute = BACKENDS[name].partition(":")
    return getattr(importlib.import_module(module), attribute)


def refusals(env) -> dict[str, str | None]:
    """Per local backend, why it cannot play ``env`` (an id or an :class:`~torchrl_esrl.envs.EnvSpec`)
    exactly as the ``gym`` reference would, or None where it can."""
    out = {}
    for name in LOCAL_BACKENDS:
        refusal = getattr(backend_class(name), "refusal", None)
        out[name] = refusal(env) if refusal is not None else None
    return out


def resolve_backend(name: str, env, fast_physics: bool = True, field: str = "es.backend", allowed=None) -> str:
    """The backend that plays ``env`` for ``name`` (``es.backend``, or ``ray.worker_backend``
    with ``allowed=LOCAL_BACKENDS``): ``auto`` resolved, the one place it is, to the fastest
    local backend for ``env`` (:func:`default_backend`), or to the ``gym`` reference without
    ``fast_physics``; an explicit ``mujoco_batch`` without ``fast_physics`` is refused (the run's
    pieces would say ``es_physics reference`` while the fast physics ran). Raises a one-line
    :class:`~torchrl_esrl.errors.ConfigError` naming ``field``."""
    allowed = list(BACKENDS if allowed is None else allowed)
    if name != "auto" and name not in allowed:
        raise ConfigError(f"{field}: unknown backend '{name}' (allowed: {', '.join(['auto', *allowed])})")
    if name == "mujoco_batch" and not fast_physics:
        others = [n for n in allowed if n != "mujoco_batch"]
        raise ConfigError(f"{field}: mujoco_batch is the fast physics (es_physics), which implementation=reference leaves out (allowed: {', '.join(['auto', *others])}, or implementation=fast)")
    if name == "auto":
        return default_backend(env) if fast_physics else "gym"
    return name


def default_backend(env) -> str:
    """The fastest local backend that plays ``env`` (an id or an :class:`~torchrl_esrl.envs.EnvSpec`)
    exactly as the ``gym`` reference would."""
    for name, refusal in reversed(refusals(env).items()):
        if refusal is None:
            return name
    return "gym"


def es_backend(cfg, pieces: Collection[str] | None = None) -> tuple[str, dict]:
    """The ES collector's backend of a config and its keyword arguments: ``es.backend`` (and, for
    ``ray``, ``ray.worker_backend``) resolved once (:func:`resolve_backend`: ``auto`` is the fastest
    local backend for the env, or the ``gym`` reference without the ``es_physics`` piece, which
    also refuses an explicit ``mujoco_batch``); ``mujoco_batch`` steps on this job's share of the
    cores (:func:`~torchrl_esrl.threads.job_cores`)."""
    spec, fast_physics = EnvSpec.from_config(cfg.env), "es_physics" in chosen_pieces(cfg, pieces)
    backend = resolve_backend(cfg.es.backend, spec, fast_physics)
    if backend == "ray":  # offspring evaluated on a Ray cluster, see the `ray` config section
        kwargs = OmegaConf.to_container(cfg.ray, resolve=True)  # its keys are RayBackend's arguments
        kwargs["worker_backend"] = resolve_backend(kwargs["worker_backend"], spec, fast_physics, "ray.worker_backend", LOCAL_BACKENDS)
        return backend, kwargs
    return backend, {"nthread": job_cores()} if backend == "mujoco_batch" else {}
