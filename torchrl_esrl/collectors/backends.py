"""The one registry of ES population backends (``es.backend``).

Each entry names where its class lives; it is imported on first use, so optional dependencies
(Ray) load only when asked for and no backend module imports another.
"""
from __future__ import annotations

import importlib
from collections.abc import Callable

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


def default_backend(env) -> str:
    """The fastest local backend that plays ``env`` (an id or an :class:`~torchrl_esrl.envs.EnvSpec`)
    exactly as the ``gym`` reference would."""
    for name, refusal in reversed(refusals(env).items()):
        if refusal is None:
            return name
    return "gym"
