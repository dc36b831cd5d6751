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


def default_backend(env_id: str) -> str:
    """The fastest local backend that supports ``env_id``."""
    for name in LOCAL_BACKENDS:
        supports = getattr(backend_class(name), "supports", None)
        if supports is not None and supports(env_id):
            return name
    return "gym"
