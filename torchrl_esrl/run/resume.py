"""Checks before any work: config values, the task, what the run will hold, the output directory
and what it already holds.

A run directory holding a checkpoint continues that run, if it is the run asked for: the same
algorithm on the same env (else one line naming both), then the same config (else one line
naming the first field that differs). ``resume=<dir>`` continues ``<dir>`` with its own config.
A finished run (``summary.json`` written, the last file a run writes) is never rewritten:
:class:`Finished` carries the line that says so. ``fresh=true`` starts a new run next to a
directory that holds one (:func:`fresh_run_dir`).
"""
from __future__ import annotations

import copy
import dataclasses
import json
import typing
from collections.abc import Callable
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from torchrl.checkpoint import Checkpoint

from torchrl_esrl.envs import EnvSizes, EnvSpec, resolve_env_id
from torchrl_esrl.errors import ConfigError
from torchrl_esrl.run.algorithm_info import AlgorithmInfo
from torchrl_esrl.run.capacity import Holding, check_capacity, estimate
from torchrl_esrl.run.checkpoint import CHECKPOINT_DIR, newest_readable, no_readable_checkpoint
from torchrl_esrl.run.config import added_keys, check_output_dir, renamed_keys, schema_of, section_of, validate_config, validate_device
from torchrl_esrl.run.schema import RunConfig

IGNORED_ON_RESUME = ("resume", "fresh", "logger", "checkpoint", "hydra")  # may change between a run and its resume
SUMMARY = "summary.json"
NEW_RUN = "fresh=true or another hydra.run.dir for a new run"


class Finished(Exception):
    """The run directory holds a finished run; the message is the one line that says so."""


def _flatten(node, prefix: str = "") -> dict:
    if isinstance(node, dict):
        out = {}
        for key, value in node.items():
            out.update(_flatten(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: node}


def finished_summary(run_dir: Path) -> dict | None:
    """``summary.json`` of a finished run in ``run_dir`` (None if the run has not finished)."""
    try:
        return json.loads((Path(run_dir) / SUMMARY).read_text())
    except (OSError, ValueError):
        return None


def holds_run(run_dir: Path) -> bool:
    run_dir = Path(run_dir)
    return any((run_dir / name).exists() for name in (SUMMARY, CHECKPOINT_DIR, "metrics.csv"))


def fresh_run_dir(run_dir) -> Path:
    """``run_dir`` if it holds no run, else the first ``<run_dir>-2``, ``-3``... that does not exist."""
    run_dir = Path(str(run_dir)).expanduser()
    number = 2
    candidate = run_dir
    while holds_run(candidate) or (candidate != run_dir and candidate.exists()):
        candidate, number = run_dir.with_name(f"{run_dir.name}-{number}"), number + 1
    return candidate


def _article(name: str) -> str:
    return "an" if name[:1].lower() in "aeiou" else "a"


def _check_identity(field: str, run_dir: Path, algorithm: str | None, env_id: str, metadata: dict | None, summary: dict | None) -> None:
    """The directory's run is ``algorithm`` (None: any) on ``env_id``, where it says (summary or checkpoint)."""
    held_algorithm = (summary or {}).get("algorithm") or (metadata or {}).get("algorithm")
    held_env = (summary or {}).get("env") or ((metadata or {}).get("config") or {}).get("env", {}).get("id")
    held_env = resolve_env_id(held_env) if held_env else None
    if (held_algorithm and algorithm and held_algorithm != algorithm) or (held_env and held_env != env_id):
        held = f"{_article(held_algorithm)} {held_algorithm} run" if held_algorithm else "a run"
        raise ConfigError(
            f"{field}: {run_dir} holds {held} on {held_env or 'an unknown env'}; asked: {algorithm} on {env_id} "
            f"(allowed: the recipe and config of that run, to continue it; {NEW_RUN}); nothing was changed"
        )


def finished_line(run_dir: Path, summary: dict) -> str:
    final = summary.get("final_return")
    result = f" (final return {final:.1f})" if isinstance(final, (int, float)) else ""
    return (
        f"finished: {run_dir} holds a finished {summary.get('algorithm', '')} run on {summary.get('env', '?')}{result}; "
        f"results in {Path(run_dir) / SUMMARY} and metrics.csv; nothing was changed ({NEW_RUN})"
    )


def _node(config: dict, key: str, create: bool = False) -> tuple[dict | None, str]:
    """The mapping holding dotted ``key`` in ``config`` (made where ``create``; None where there is none), and the key's last part."""
    *parents, name = key.split(".")
    for part in parents:
        if not isinstance(config.get(part), dict):
            if not create:
                return None, name
            config[part] = {}
        config = config[part]
    return config, name


def _in_schema(saved: dict, schema) -> dict:
    """The keys of ``saved`` that ``schema`` defines, section by section (open mappings whole)."""
    hints = typing.get_type_hints(schema)
    kept = {}
    for item in dataclasses.fields(schema):
        if item.name in saved:
            value, section = saved[item.name], section_of(hints[item.name])
            kept[item.name] = _in_schema(value, section) if section is not None and isinstance(value, dict) else value
    return kept


def in_todays_names(saved: dict, schema=None) -> dict:
    """A checkpoint's config in today's key names, so that a run started before a rename or an
    added key resumes: the renamed and added keys of the recipe's ``schema`` (``run/config.py``'s
    :func:`renamed_keys` and :func:`added_keys`; by default every run's): ``td3.fast: true|false``
    is ``implementation: fast|reference``, the top-level ``mode`` is ``es.schedule``, a missing
    ``env.kwargs`` is ``{}``. With a ``schema``, the keys it does not define are left out: a
    section the recipe does not have, which its runs saved, null, when every recipe's config held
    every section, and nothing of the recipe read."""
    saved = copy.deepcopy(saved) if schema is None else _in_schema(copy.deepcopy(saved), schema)
    schema = RunConfig if schema is None else schema
    for old, new in renamed_keys(schema).items():
        section, name = _node(saved, old)
        if section is not None and section.get(name) is not None:
            target, to_name = _node(saved, new.to, create=True)
            target[to_name], section[name] = new.convert(section[name]), None
    for key, value in added_keys(schema).items():  # keys a config saved before they existed had at these values
        section, name = _node(saved, key)
        if section is not None and name not in section:
            section[name] = copy.deepcopy(value)
    return saved


def check_saved_device(run_dir: Path, device) -> None:
    """A run resumes on the device it was written on: its checkpoint holds that device's tensors and
    random streams (the CUDA generator's state on ``cuda``), which another device cannot continue
    exactly. In a run directory another ``device`` is refused as any other changed key is; with
    ``resume=<dir>`` the run's own device must be available here."""
    try:
        validate_device(device)
    except ConfigError:
        raise ConfigError(
            f"device: {run_dir} was written with device={device}, which this machine lacks; a run resumes on the device it was "
            f"written on (allowed: resume it where {device} is available, or {NEW_RUN}); nothing was changed"
        ) from None


def algorithm_of(algorithm: AlgorithmInfo | Callable[[DictConfig], AlgorithmInfo], cfg: DictConfig) -> AlgorithmInfo:
    """The :class:`AlgorithmInfo` a recipe runs with ``cfg`` (a recipe with variants passes a function)."""
    return algorithm(cfg) if callable(algorithm) else algorithm


def prepare_run(
    cfg: DictConfig,
    hydra_run_dir,
    algorithm: AlgorithmInfo | Callable[[DictConfig], AlgorithmInfo] | None = None,
    holdings: Callable[[DictConfig, EnvSizes], list[Holding]] | None = None,
) -> tuple[DictConfig, Path]:
    """Every check before any work. Returns ``(config, run_dir)``; raises :class:`ConfigError`
    with a one-line message, or :class:`Finished` if the run directory's run has finished.

    ``algorithm`` and ``holdings`` are the recipe's, as given to ``recipe_main``: what it runs
    (the run directory must hold a run of it, if any) and what it will hold (checked against
    this machine's memory and disk; :mod:`~torchrl_esrl.run.capacity`); without them, neither
    is checked. ``resume=<dir>`` continues
    ``<dir>`` with the config saved in its checkpoint (``logger`` and ``checkpoint`` settings
    from the command line).
    """
    resume, schema = cfg.resume, schema_of(cfg)  # the recipe's schema, as Hydra composed its config
    if resume and cfg.get("fresh"):
        raise ConfigError(f"fresh: true asks for a new run, resume={resume} to continue one (allowed: one of them)")
    field = "resume" if resume else "hydra.run.dir"
    run_dir = Path(str(resume if resume else hydra_run_dir)).expanduser()
    readable, damaged = newest_readable(run_dir) if run_dir.is_dir() else (None, [])
    metadata = Checkpoint.manifest(readable)["metadata"] if readable is not None else None
    summary = finished_summary(run_dir)
    saved = in_todays_names(metadata["config"], schema) if metadata is not None else None
    current = OmegaConf.to_container(OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"]), resolve=True)
    if resume and saved is None:
        if summary is not None:
            raise Finished(finished_line(run_dir, summary))
        if damaged:
            raise ConfigError(f"resume: {no_readable_checkpoint(run_dir, damaged)}")
        raise ConfigError(f"resume: '{resume}' holds no checkpoint (allowed: a run directory with a {CHECKPOINT_DIR}/ folder)")
    if resume:
        for key in IGNORED_ON_RESUME:
            if key in current:
                saved[key] = current[key]
        cfg = OmegaConf.create(saved)
        check_saved_device(run_dir, cfg.get("device", "cpu"))
    validate_config(cfg, schema)
    name = algorithm_of(algorithm, cfg).name if algorithm is not None else None
    sizes = EnvSpec.from_config(cfg.env).checked_sizes()  # the env played in a child process: refuses what the algorithms cannot take or it cannot play
    _check_identity(field, run_dir, name, resolve_env_id(cfg.env.id), metadata, summary)
    if saved is not None and not resume:
        before, now = _flatten({k: v for k, v in saved.items() if k not in IGNORED_ON_RESUME}), _flatten({k: v for k, v in current.items() if k not in IGNORED_ON_RESUME})
        for key in sorted(set(before) | set(now)):
            if before.get(key, "<absent>") != now.get(key, "<absent>"):
                raise ConfigError(
                    f"{key}: {now.get(key, '<absent>')!r} differs from {before.get(key, '<absent>')!r} in the checkpoint of {run_dir} "
                    "(allowed: the run's own config to resume it, or another hydra.run.dir)"
                )
    if summary is not None:
        raise Finished(finished_line(run_dir, summary))
    if readable is None and damaged:
        raise ConfigError(f"{field}: {no_readable_checkpoint(run_dir, damaged)}")
    if readable is None and (run_dir / "metrics.csv").exists():
        raise ConfigError(f"{field}: {run_dir} holds metrics.csv but no checkpoint to continue it from; nothing was changed (allowed: {NEW_RUN})")
    if holdings is not None:
        check_capacity(cfg, estimate(holdings(cfg, sizes)), run_dir)
    check_output_dir(run_dir)
    return cfg, run_dir
