"""Value checks of every config key, run before any environment, network, buffer or file is made.

Each failure is a :class:`~torchrl_esrl.errors.ConfigError` with one line,
``<field>: <value> ... (allowed: ...)``. Types and unknown keys are the typed schema's job
(:mod:`torchrl_esrl.run.schema`); this module checks values: ranges, choices, that the device
exists, that the logger's package is installed, and that the run directory can be written.
"""
from __future__ import annotations

import importlib.util
import math
import os
from collections.abc import Mapping
from pathlib import Path

from torchrl_esrl.errors import ConfigError

# Choices of the enumerated keys (where the component owning a name list has one, it is used instead).
LOSS_FUNCTIONS = ("l2", "l1", "smooth_l1")  # torchrl.objectives.utils.distance_loss
FITNESS_SHAPINGS = ("centered_ranks", "none")  # torchrl_esrl.es.openes.OpenES
BUFFER_MODES = ("multi", "shared")
SCHEDULES = ("sequential", "async")
OVERWRITE_MODES = ("hard", "soft")
# logger.backend -> the package its TorchRL logger needs ("" = no logger, csv = no extra package)
LOGGER_PACKAGES = {"": None, "csv": None, "tensorboard": "tensorboard", "wandb": "wandb", "mlflow": "mlflow", "trackio": "trackio"}
SEED_LIMIT = 2**31 - 2000  # numpy seeds are < 2**32; the recipes add up to 1000 for their streams


# Keys that were renamed: old name -> what to write instead (the schema keeps the old name, unset, so
# that a config using it reaches this check instead of Hydra's unknown-key error).
RENAMED = {
    "td3.fast": "implementation (implementation=fast, or implementation=reference for td3.fast=false)",
    "mode": "es.schedule (es.schedule=sequential or es.schedule=async)",
}


# Keys added to the schema since runs were first checkpointed: key -> the value a config saved before
# it existed had in effect, so that such a run resumes under today's config.
ADDED = {"env.kwargs": {}, "env.wrappers": [], "env.transforms": []}


def _get_or_none(cfg, field: str):
    try:
        return _get(cfg, field)
    except (KeyError, AttributeError):
        return None


def _get(cfg, field: str):
    node = cfg
    for part in field.split("."):
        node = node[part]
    return node


def _is_number(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)


def _number(cfg, field: str, low=None, high=None, low_open=False, high_open=False, integer=False) -> None:
    """``field`` is a finite number (an integer if ``integer``) within the given bounds."""
    value = _get(cfg, field)
    ok = _is_number(value) and (not integer or float(value).is_integer())
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value < high if high_open else value <= high
    if not ok:
        kind = "an integer" if integer else "a number"
        if low is not None and high is not None:
            allowed = f"{kind} in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
        elif low is not None:
            allowed = f"{kind} {'>' if low_open else '>='} {low:g}"
        else:
            allowed = kind
        raise ConfigError(f"{field}: {value!r} is invalid (allowed: {allowed})")


def _positive(cfg, field: str, integer: bool = False) -> None:
    _number(cfg, field, low=0, low_open=True, integer=integer)


def _choice(cfg, field: str, options) -> None:
    value = _get(cfg, field)
    if value not in options:
        raise ConfigError(f"{field}: {value!r} is invalid (allowed: {', '.join(repr(o) if o == '' else str(o) for o in options)})")


def _layers(cfg, field: str) -> None:
    value = list(_get(cfg, field))
    if not value or not all(_is_number(v) and float(v).is_integer() and v > 0 for v in value):
        raise ConfigError(f"{field}: {value!r} is invalid (allowed: a non-empty list of positive integers, e.g. [256, 256])")


def check_known_keys(cfg, path: str = "") -> None:
    """Every key of ``cfg`` is one the typed schema defines, whatever the override syntax: Hydra
    refuses ``key=value`` for a key the schema lacks, but ``+key=value`` and ``++key=value``
    add it, and nothing would read it. Mappings typed ``Dict[str, Any]`` or ``Any`` in the schema
    (``env.kwargs``, ``ray.worker_kwargs``) are open."""
    import dataclasses

    from omegaconf import DictConfig, OmegaConf

    schema = OmegaConf.get_type(cfg)
    if not dataclasses.is_dataclass(schema):
        return
    fields = {f.name for f in dataclasses.fields(schema)}
    for key in cfg.keys():
        name = f"{path}{key}"
        if not path and key == "hydra":  # Hydra's own node, beside the schema's in the launch config
            continue
        if key not in fields:
            raise ConfigError(f"{name}: not a key of this config (allowed: {', '.join(sorted(fields))})")
        if OmegaConf.is_missing(cfg, key):
            continue
        value = cfg.get(key)
        if isinstance(value, DictConfig):
            check_known_keys(value, f"{name}.")


def validate_config(cfg) -> None:
    """Value checks of every key of ``conf/config.yaml`` (and ``conf/cem_rl.yaml``'s ``cem``)."""
    check_known_keys(cfg)
    from torchrl_esrl.collectors.backends import LOCAL_BACKENDS, available_backends
    from torchrl_esrl.data.multibuffer import validate_ratio
    from torchrl_esrl.envs import resolve_env_id
    from torchrl_esrl.modules.networks import ACTIVATIONS
    from torchrl_esrl.run.factories import IMPLEMENTATIONS

    for old, new in RENAMED.items():
        if _get_or_none(cfg, old) is not None:
            raise ConfigError(f"{old}: renamed to {new}")
    _number(cfg, "seed", low=0, high=SEED_LIMIT, integer=True)
    _choice(cfg, "implementation", IMPLEMENTATIONS)
    if not str(cfg.experiment_name).strip():
        raise ConfigError("experiment_name: '' is invalid (allowed: a non-empty name)")
    validate_device(cfg.device)
    resolve_env_id(cfg.env.id)
    if cfg.env.max_episode_steps is not None:
        _positive(cfg, "env.max_episode_steps", integer=True)
    for field in ("iterations", "td3.frames_per_iteration", "td3.frames_per_batch", "td3.policy_delay", "eval.episodes", "eval.final_episodes", "overwrite.window"):
        _positive(cfg, field, integer=True)

    # TD3 (Fujimoto et al. 2018; TorchRL's TD3Loss and SoftUpdate)
    for field in ("td3.lr", "td3.updates_per_frame"):
        _positive(cfg, field)
    _number(cfg, "td3.gamma", low=0, high=1)
    _number(cfg, "td3.tau", low=0, high=1, low_open=True)
    for field in ("td3.policy_noise", "td3.noise_clip", "td3.exploration_noise"):
        _number(cfg, field, low=0)
    _choice(cfg, "td3.loss_function", LOSS_FUNCTIONS)
    if cfg.td3.num_threads is not None:  # null: the job's share of the cores (torchrl_esrl/threads.py)
        _number(cfg, "td3.num_threads", low=1, integer=True)
    _layers(cfg, "td3.critic_hidden")
    _choice(cfg, "td3.critic_activation", sorted(ACTIVATIONS))
    _layers(cfg, "actor.hidden")
    _choice(cfg, "actor.activation", sorted(ACTIVATIONS))
    if cfg.td3.frames_per_iteration % cfg.td3.frames_per_batch:
        raise ConfigError(f"td3.frames_per_batch: {cfg.td3.frames_per_batch} does not divide td3.frames_per_iteration={cfg.td3.frames_per_iteration} (allowed: a divisor)")

    # OpenAI-ES
    for field in ("es.generations_per_iteration", "es.population_size"):
        _positive(cfg, field, integer=True)
    for field in ("es.sigma", "es.lr"):
        _positive(cfg, field)
    _number(cfg, "es.weight_decay", low=0)
    _choice(cfg, "es.fitness_shaping", FITNESS_SHAPINGS)
    _choice(cfg, "es.backend", available_backends())
    if cfg.es.backend == "mujoco_batch":
        from torchrl_esrl.collectors.mujoco_batch import MujocoBatchBackend
        from torchrl_esrl.envs import EnvSpec

        reason = MujocoBatchBackend.refusal(EnvSpec.from_config(cfg.env))
        if reason is not None:
            raise ConfigError(f"es.backend: mujoco_batch cannot play this env exactly as gymnasium would ({reason}) (allowed: auto, gym)")
    if cfg.es.antithetic and cfg.es.population_size % 2:
        raise ConfigError(f"es.population_size: {cfg.es.population_size} is invalid with es.antithetic=true (allowed: an even positive integer)")
    if cfg.es.backend == "ray":
        _package("es.backend", "ray", "ray")
    _positive(cfg, "ray.num_workers", integer=True)
    _positive(cfg, "ray.num_cpus_per_worker")
    _choice(cfg, "ray.worker_backend", ["auto", *LOCAL_BACKENDS])
    address = cfg.ray.address
    if address is not None and address != "auto" and not _is_host_port(address):
        raise ConfigError(f"ray.address: {address!r} is invalid (allowed: null to start Ray here, auto, or host:port)")
    if not isinstance(cfg.ray.worker_kwargs, Mapping):
        raise ConfigError(f"ray.worker_kwargs: {cfg.ray.worker_kwargs!r} is invalid (allowed: a mapping of keyword arguments, e.g. {{}})")

    # MultiBuffer (Section 3.1), threshold, overwrite rule (Section 3.2)
    validate_ratio(cfg.buffer.ratio)
    for field in ("buffer.capacity", "buffer.batch_size", "buffer.min_size"):
        _positive(cfg, field, integer=True)
    if cfg.buffer.capacity < cfg.buffer.batch_size:
        raise ConfigError(f"buffer.capacity: {cfg.buffer.capacity} is smaller than buffer.batch_size={cfg.buffer.batch_size} (allowed: >= batch_size)")
    if cfg.buffer.min_size < cfg.buffer.batch_size:
        raise ConfigError(f"buffer.min_size: {cfg.buffer.min_size} is smaller than buffer.batch_size={cfg.buffer.batch_size} (allowed: K >= batch_size)")
    if cfg.buffer.min_size > cfg.buffer.capacity:
        raise ConfigError(f"buffer.min_size: {cfg.buffer.min_size} is larger than buffer.capacity={cfg.buffer.capacity} (allowed: K <= capacity, else TD3 never starts)")
    _choice(cfg, "buffer.mode", BUFFER_MODES)
    _number(cfg, "threshold.fraction", low=0, high=1)
    _choice(cfg, "es.schedule", SCHEDULES)
    _choice(cfg, "overwrite.mode", OVERWRITE_MODES)
    _number(cfg, "overwrite.mix", low=0, high=1, low_open=True)
    _number(cfg, "td3.random_frames", low=0, integer=True)

    # Run plumbing: logger, checkpoints
    _choice(cfg, "logger.backend", list(LOGGER_PACKAGES))
    if LOGGER_PACKAGES[cfg.logger.backend]:
        _package("logger.backend", cfg.logger.backend, LOGGER_PACKAGES[cfg.logger.backend])
    _number(cfg, "checkpoint.every_frames", low=0, integer=True)
    _positive(cfg, "checkpoint.keep_last", integer=True)

    if cfg.get("cem") is not None:  # CEM-RL baseline (conf/cem_rl.yaml)
        _number(cfg, "cem.population_size", low=2, integer=True)
        _number(cfg, "cem.rl_fraction", low=0, high=1)
        _number(cfg, "cem.elite_fraction", low=0, high=1, low_open=True)
        _positive(cfg, "cem.sigma_init")
        for field in ("cem.damping_init", "cem.damping_end"):
            _number(cfg, field, low=0)
        _number(cfg, "cem.damping_tau", low=0, high=1)
        _number(cfg, "cem.start_frames", low=0, integer=True)


def _is_host_port(address) -> bool:
    host, _, port = str(address).rpartition(":")
    return bool(host) and port.isdigit() and 0 < int(port) < 65536


def _package(field: str, value: str, package: str) -> None:
    if importlib.util.find_spec(package) is None:
        raise ConfigError(f"{field}: {value!r} needs the '{package}' package, which is not installed (allowed: install it, e.g. pip install {package}, or choose another)")


def validate_device(device) -> None:
    """``device`` names a device torch can use here: ``cpu``, or ``cuda``/``cuda:N`` where CUDA exists."""
    import torch

    allowed = "cpu" + (f", cuda, cuda:0..{torch.cuda.device_count() - 1}" if torch.cuda.is_available() else "; CUDA is not available on this machine")
    try:
        parsed = torch.device(str(device))
    except (RuntimeError, ValueError):
        raise ConfigError(f"device: {device!r} is not a device name (allowed: {allowed})") from None
    if parsed.type == "cpu":
        return
    if parsed.type != "cuda" or not torch.cuda.is_available() or (parsed.index or 0) >= torch.cuda.device_count():
        raise ConfigError(f"device: {device!r} is not available (allowed: {allowed})")


def check_output_dir(path) -> None:
    """The run directory exists and is writable, or is created now (what Hydra does next anyway).

    Creating it is the only check that also holds for root, read-only mounts and ACLs; nothing
    inside an existing directory is touched."""
    path = Path(path).absolute()
    if path.exists() and not path.is_dir():
        raise ConfigError(f"hydra.run.dir: '{path}' is a file (allowed: a writable directory)")
    existing = path
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise ConfigError(f"hydra.run.dir: '{path}' cannot be created: '{existing}' is a file (allowed: a writable directory)")
    if path.is_dir():
        if not os.access(path, os.W_OK | os.X_OK):
            raise ConfigError(f"hydra.run.dir: '{path}' is not writable (allowed: a writable directory)")
        return
    try:
        path.mkdir(parents=True)
    except OSError as error:
        raise ConfigError(f"hydra.run.dir: '{path}' cannot be created ({error.strerror}; allowed: a writable directory)") from None
