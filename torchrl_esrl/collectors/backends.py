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


def refusals(env, population_actor=None) -> dict[str, str | None]:
    """Per local backend, why it cannot play ``env`` (an id or an :class:`~torchrl_esrl.envs.EnvSpec`),
    and the members of ``population_actor`` where given, exactly as the ``gym`` reference would,
    or None where it can."""
    return {name: _refusal(name, env, population_actor) for name in LOCAL_BACKENDS}


def _refusal(name: str, env, population_actor) -> str | None:
    cls = backend_class(name)
    refusal, policy_refusal = getattr(cls, "refusal", None), getattr(cls, "policy_refusal", None)
    reason = refusal(env) if refusal is not None else None
    if reason is None and population_actor is not None and policy_refusal is not None:
        reason = policy_refusal(population_actor, env)
    return reason


def resolve_backend(name: str, env, fast_physics: bool = True, field: str = "es.backend", allowed=None, population_actor=None) -> str:
    """The backend that plays ``env`` for ``name`` (``es.backend``, or ``ray.worker_backend``
    with ``allowed=LOCAL_BACKENDS``): ``auto`` resolved, the one place it is, to the fastest
    local backend for ``env`` and ``population_actor`` (:func:`default_backend`), or to the
    ``gym`` reference without ``fast_physics``; an explicit ``mujoco_batch`` without
    ``fast_physics`` is refused (the run's pieces would say ``es_physics reference`` while the
    fast physics ran), as is an explicit backend that cannot play ``population_actor``'s members
    as the reference would (a policy that is not a deterministic function of its observation, in
    worker threads). Raises a one-line :class:`~torchrl_esrl.errors.ConfigError` naming ``field``."""
    allowed = list(BACKENDS if allowed is None else allowed)
    if name != "auto" and name not in allowed:
        raise ConfigError(f"{field}: unknown backend '{name}' (allowed: {', '.join(['auto', *allowed])})")
    if name == "mujoco_batch" and not fast_physics:
        others = [n for n in allowed if n != "mujoco_batch"]
        raise ConfigError(f"{field}: mujoco_batch is the fast physics (es_physics), which implementation=reference leaves out (allowed: {', '.join(['auto', *others])}, or implementation=fast)")
    if name in LOCAL_BACKENDS and population_actor is not None:
        policy_refusal = getattr(backend_class(name), "policy_refusal", None)
        reason = policy_refusal(population_actor, env) if policy_refusal is not None else None
        if reason is not None:
            others = [n for n in allowed if n != name]
            raise ConfigError(f"{field}: {name} cannot play this actor exactly as the gym reference would ({reason}) (allowed: {', '.join(['auto', *others])})")
    if name == "auto":
        return default_backend(env, population_actor) if fast_physics else "gym"
    return name


def default_backend(env, population_actor=None) -> str:
    """The fastest local backend that plays ``env`` (an id or an :class:`~torchrl_esrl.envs.EnvSpec`),
    and the members of ``population_actor`` where given, exactly as the ``gym`` reference would."""
    for name, refusal in reversed(refusals(env, population_actor).items()):
        if refusal is None:
            return name
    return "gym"


def es_backend(cfg, pieces: Collection[str] | None = None, population_actor=None) -> tuple[str, dict]:
    """The ES collector's backend of a config and its keyword arguments: ``es.backend`` (and, for
    ``ray``, ``ray.worker_backend``) resolved once (:func:`resolve_backend`: ``auto`` is the fastest
    local backend for the env and the members' forward ``population_actor``, or the ``gym``
    reference without the ``es_physics`` piece, which also refuses an explicit ``mujoco_batch``);
    ``mujoco_batch`` steps on this job's share of the cores (:func:`~torchrl_esrl.threads.job_cores`)."""
    spec, fast_physics = EnvSpec.from_config(cfg.env), "es_physics" in chosen_pieces(cfg, pieces)
    backend = resolve_backend(cfg.es.backend, spec, fast_physics, population_actor=population_actor)
    if backend == "ray":  # offspring evaluated on a Ray cluster, see the `ray` config section
        kwargs = OmegaConf.to_container(cfg.ray, resolve=True)  # its keys are RayBackend's arguments
        kwargs["worker_backend"] = resolve_backend(kwargs["worker_backend"], spec, fast_physics, "ray.worker_backend", LOCAL_BACKENDS, population_actor)
        return backend, kwargs
    return backend, {"nthread": job_cores()} if backend == "mujoco_batch" else {}
