"""Value checks of every config key, run before any environment, network, buffer or file is made.

Each failure is a :class:`~torchrl_esrl.errors.ConfigError` with one line,
``<field>: <value> ... (allowed: ...)``. Types and unknown keys are the typed schema's job
(:mod:`torchrl_esrl.run.schema`: every run's keys, and a recipe's own sections), and so is each
key's own check: :func:`validate_config` walks the schema's fields and runs the check each one
carries (a range, a choice, a function) and each section's checks across its own keys, then the
checks that relate sections to each other, listed here. The renamed keys (:func:`renamed_keys`)
and the keys added since runs were first checkpointed (:func:`added_keys`) are read from the
schema too.
"""
from __future__ import annotations

import dataclasses
import importlib.util
import math
import os
import typing
from collections.abc import Iterator, Mapping
from pathlib import Path

from hydra.utils import get_object
from omegaconf import DictConfig, OmegaConf

from torchrl_esrl.errors import ConfigError
from torchrl_esrl.run.schema import Renamed, RunConfig


def section_of(annotation):
    """The dataclass of a section's annotation (``Optional[CEMConfig]`` -> ``CEMConfig``), else None."""
    for candidate in (annotation, *typing.get_args(annotation)):
        if dataclasses.is_dataclass(candidate):
            return candidate
    return None


def schema_fields(schema=RunConfig, prefix: str = "") -> Iterator[tuple[str, dataclasses.Field, object]]:
    """``(key, field, annotation)`` of every key of ``schema``, sections first-class: a section is
    yielded, then its keys."""
    hints = typing.get_type_hints(schema)
    for item in dataclasses.fields(schema):
        key = f"{prefix}{item.name}"
        yield key, item, hints[item.name]
        section = section_of(hints[item.name])
        if section is not None:
            yield from schema_fields(section, f"{key}.")


def _default(item: dataclasses.Field):
    value = item.default_factory() if item.default_factory is not dataclasses.MISSING else item.default
    return dataclasses.asdict(value) if dataclasses.is_dataclass(value) else value  # a section: its keys


def renamed_keys(schema=RunConfig) -> dict[str, Renamed]:
    """Keys of ``schema`` that were renamed: old name -> what replaced it (the schema keeps the old
    name, unset, so that a config using it reaches this check instead of Hydra's unknown-key error)."""
    return {key: item.metadata["renamed"] for key, item, _ in schema_fields(schema) if "renamed" in item.metadata}


def added_keys(schema=RunConfig) -> dict[str, object]:
    """Keys added to ``schema`` since runs were first checkpointed: key -> the value a config saved
    before it existed had in effect, so that such a run resumes under today's config."""
    return {key: _default(item) for key, item, _ in schema_fields(schema) if item.metadata.get("added")}


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


def _number(field: str, value, low=None, high=None, low_open=False, high_open=False, integer=False) -> None:
    """``value`` is a finite number (an integer if ``integer``) within the given bounds."""
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


def _choice(field: str, value, options=(), among=None, packages=None) -> None:
    if among is not None:
        named = get_object(among)
        named = named() if callable(named) else named
        options = [*options, *(sorted(named) if isinstance(named, Mapping) else named)]
    if value not in options:
        raise ConfigError(f"{field}: {value!r} is invalid (allowed: {', '.join(repr(o) if o == '' else str(o) for o in options)})")
    if (packages or {}).get(value):
        _package(field, value, packages[value])


def _layers(field: str, value) -> None:
    value = list(value)
    if not value or not all(_is_number(v) and float(v).is_integer() and v > 0 for v in value):
        raise ConfigError(f"{field}: {value!r} is invalid (allowed: a non-empty list of positive integers, e.g. [256, 256])")


def _name(field: str, value) -> None:
    if not str(value).strip():
        raise ConfigError(f"{field}: {value!r} is invalid (allowed: a non-empty name)")


def _host_port(field: str, value) -> None:
    if value != "auto" and not _is_host_port(value):
        raise ConfigError(f"{field}: {value!r} is invalid (allowed: null to start Ray here, auto, or host:port)")


def _mapping(field: str, value) -> None:
    if not isinstance(value, Mapping):
        raise ConfigError(f"{field}: {value!r} is invalid (allowed: a mapping of keyword arguments, e.g. {{}})")


def _call(field: str, value, function: str) -> None:
    get_object(function)(value)


CHECKS = {"number": _number, "choice": _choice, "layers": _layers, "name": _name, "host_port": _host_port, "mapping": _mapping, "call": _call}


def schema_of(cfg):
    """The schema ``cfg`` was composed with (a recipe's, or :class:`RunConfig`); an untyped config is read as RunConfig."""
    schema = OmegaConf.get_type(cfg)
    return schema if dataclasses.is_dataclass(schema) else RunConfig


def check_fields(cfg, schema=None, prefix: str = "") -> None:
    """Each key's own check, as its schema field carries it (:mod:`torchrl_esrl.run.schema`), in the
    schema's order, and after a section's keys its ``check(section, key)``, where it has one.
    ``schema``: by default the config's own (:func:`schema_of`). A section or an Optional key that
    is null is not checked."""
    schema = schema_of(cfg) if schema is None else schema
    hints = typing.get_type_hints(schema)
    for item in dataclasses.fields(schema):
        key, value = f"{prefix}{item.name}", cfg[item.name]
        if value is None and type(None) in typing.get_args(hints[item.name]):  # an Optional key, unset
            continue
        section = section_of(hints[item.name])
        if section is not None:
            check_fields(value, section, f"{key}.")
            if callable(getattr(section, "check", None)):
                section.check(value, key)
        elif "check" in item.metadata:
            check = dict(item.metadata["check"])
            CHECKS[check.pop("kind")](key, value, **check)


def check_known_keys(cfg, path: str = "") -> None:
    """Every key of ``cfg`` is one the typed schema defines, whatever the override syntax: Hydra
    refuses ``key=value`` for a key the schema lacks, but ``+key=value`` and ``++key=value``
    add it, and nothing would read it. Mappings typed ``Dict[str, Any]`` or ``Any`` in the schema
    (``env.kwargs``, ``ray.worker_kwargs``) are open."""
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


def validate_config(cfg, schema=None) -> None:
    """Every key's check (:func:`check_fields`), then the checks across sections. ``schema``: the
    recipe's (:func:`torchrl_esrl.run.schema.recipe_schema`), by default the one ``cfg`` was composed with."""
    schema = schema_of(cfg) if schema is None else schema
    check_known_keys(cfg)
    for old, new in renamed_keys(schema).items():
        if _get_or_none(cfg, old) is not None:
            raise ConfigError(f"{old}: renamed to {new.to} ({new.how})")
    check_fields(cfg, schema)

    td3, es, buffer = cfg.td3, cfg.es, cfg.buffer
    if td3.frames_per_iteration % td3.frames_per_batch:
        raise ConfigError(f"td3.frames_per_batch: {td3.frames_per_batch} does not divide td3.frames_per_iteration={td3.frames_per_iteration} (allowed: a divisor)")
    if es.backend == "mujoco_batch":
        from torchrl_esrl.collectors.mujoco_batch import MujocoBatchBackend
        from torchrl_esrl.envs import EnvSpec

        reason = MujocoBatchBackend.refusal(EnvSpec.from_config(cfg.env))
        if reason is not None:
            raise ConfigError(f"es.backend: mujoco_batch cannot play this env exactly as gymnasium would ({reason}) (allowed: auto, gym)")
    if "mujoco_batch" in (es.backend, cfg.ray.worker_backend) and cfg.implementation != "fast":
        from torchrl_esrl.collectors.backends import LOCAL_BACKENDS, resolve_backend

        resolve_backend(es.backend, cfg.env.id, fast_physics=False)  # the fast physics under the reference: refused
        resolve_backend(cfg.ray.worker_backend, cfg.env.id, fast_physics=False, field="ray.worker_backend", allowed=LOCAL_BACKENDS)
    if es.antithetic and es.population_size % 2:
        raise ConfigError(f"es.population_size: {es.population_size} is invalid with es.antithetic=true (allowed: an even positive integer)")
    # MultiBuffer (Section 3.1): K and the capacity against the batch size
    if buffer.capacity < buffer.batch_size:
        raise ConfigError(f"buffer.capacity: {buffer.capacity} is smaller than buffer.batch_size={buffer.batch_size} (allowed: >= batch_size)")
    if buffer.min_size < buffer.batch_size:
        raise ConfigError(f"buffer.min_size: {buffer.min_size} is smaller than buffer.batch_size={buffer.batch_size} (allowed: K >= batch_size)")
    if buffer.min_size > buffer.capacity:
        raise ConfigError(f"buffer.min_size: {buffer.min_size} is larger than buffer.capacity={buffer.capacity} (allowed: K <= capacity, else TD3 never starts)")


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
