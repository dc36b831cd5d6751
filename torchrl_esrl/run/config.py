"""Configuration errors and checks run before any expensive work starts."""
from __future__ import annotations

from torchrl_esrl.errors import ConfigError


def _positive(cfg, field: str, integer: bool = False) -> None:
    value = _get(cfg, field)
    kind = "integer" if integer else "number"
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (integer and not float(value).is_integer()) or not value > 0:
        raise ConfigError(f"{field}: {value!r} is invalid (allowed: a positive {kind})")


def _get(cfg, field: str):
    node = cfg
    for part in field.split("."):
        node = node[part]
    return node


def validate_config(cfg) -> None:
    """Value checks run before any environment, network or buffer is built."""
    from torchrl_esrl.data.multibuffer import validate_ratio
    from torchrl_esrl.envs import resolve_env_id

    resolve_env_id(cfg.env.id)
    validate_ratio(cfg.buffer.ratio)
    for field in ("td3.lr", "td3.tau", "es.sigma", "es.lr"):
        _positive(cfg, field)
    for field in ("iterations", "td3.frames_per_iteration", "td3.frames_per_batch", "es.population_size", "buffer.capacity", "buffer.batch_size", "eval.episodes", "eval.final_episodes", "overwrite.window", "td3.policy_delay"):
        _positive(cfg, field, integer=True)
    if cfg.es.antithetic and cfg.es.population_size % 2:
        raise ConfigError(f"es.population_size: {cfg.es.population_size} is invalid with es.antithetic=true (allowed: an even positive integer)")
    if cfg.td3.frames_per_iteration % cfg.td3.frames_per_batch:
        raise ConfigError(f"td3.frames_per_batch: {cfg.td3.frames_per_batch} does not divide td3.frames_per_iteration={cfg.td3.frames_per_iteration} (allowed: a divisor)")
    if cfg.buffer.capacity < cfg.buffer.batch_size:
        raise ConfigError(f"buffer.capacity: {cfg.buffer.capacity} is smaller than buffer.batch_size={cfg.buffer.batch_size} (allowed: >= batch_size)")
    if cfg.buffer.min_size < cfg.buffer.batch_size:
        raise ConfigError(f"buffer.min_size: {cfg.buffer.min_size} is smaller than buffer.batch_size={cfg.buffer.batch_size} (allowed: K >= batch_size)")
    if cfg.buffer.get("mode", "multi") not in ("multi", "shared"):
        raise ConfigError(f"buffer.mode: {cfg.buffer.mode!r} is invalid (allowed: multi, shared)")
    if not 0 <= cfg.threshold.fraction <= 1:
        raise ConfigError(f"threshold.fraction: {cfg.threshold.fraction} is invalid (allowed: a number in [0, 1])")
    if cfg.get("mode", "sequential") not in ("sequential", "async"):
        raise ConfigError(f"mode: {cfg.mode!r} is invalid (allowed: sequential, async)")
    if isinstance(cfg.td3.random_frames, bool) or not isinstance(cfg.td3.random_frames, int) or cfg.td3.random_frames < 0:
        raise ConfigError(f"td3.random_frames: {cfg.td3.random_frames!r} is invalid (allowed: 0 or a positive integer)")
    if cfg.overwrite.mode not in ("hard", "soft"):
        raise ConfigError(f"overwrite.mode: {cfg.overwrite.mode!r} is invalid (allowed: hard, soft)")
    if isinstance(cfg.overwrite.mix, bool) or not isinstance(cfg.overwrite.mix, (int, float)) or not 0 < cfg.overwrite.mix <= 1:
        raise ConfigError(f"overwrite.mix: {cfg.overwrite.mix!r} is invalid (allowed: a number in (0, 1])")
    validate_run_settings(cfg)


def validate_run_settings(cfg) -> None:
    """Checks of the keys added by issue #5 (iteration counts, checkpoints)."""
    _positive(cfg, "es.generations_per_iteration", integer=True)
    _positive(cfg, "buffer.min_size", integer=True)
    every = cfg.get("checkpoint", {}).get("every_frames", 0)
    if isinstance(every, bool) or not isinstance(every, int) or every < 0:
        raise ConfigError(f"checkpoint.every_frames: {every!r} is invalid (allowed: 0 to disable, or a positive integer)")
    if "checkpoint" in cfg:
        _positive(cfg, "checkpoint.keep_last", integer=True)


def check_output_dir(path) -> None:
    """The run directory exists and is writable, or can be created."""
    import os
    from pathlib import Path

    path = Path(path).absolute()
    if path.exists() and not path.is_dir():
        raise ConfigError(f"hydra.run.dir: '{path}' is a file (allowed: a writable directory)")
    existing = path
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(f"hydra.run.dir: '{path}' cannot be written ('{existing}' is not writable; allowed: a writable directory)")
