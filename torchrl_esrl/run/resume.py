"""Checks before any work: config values, the output directory and, in a run directory that holds
a checkpoint, that the config is the run's own (or ``resume=<dir>``: continue that run)."""
from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from torchrl_esrl.errors import ConfigError
from torchrl_esrl.run.checkpoint import CHECKPOINT_DIR, saved_config
from torchrl_esrl.run.config import check_output_dir, validate_config

IGNORED_ON_RESUME = ("resume", "logger", "checkpoint", "hydra")  # may change between a run and its resume


def _flatten(node, prefix: str = "") -> dict:
    if isinstance(node, dict):
        out = {}
        for key, value in node.items():
            out.update(_flatten(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: node}


def prepare_run(cfg: DictConfig, hydra_run_dir) -> tuple[DictConfig, Path]:
    """Every check before any work. Returns ``(config, run_dir)``; raises :class:`ConfigError`
    with a one-line message.

    ``resume=<dir>`` continues ``<dir>`` with the config saved in its checkpoint (``logger``
    and ``checkpoint`` settings from the command line).
    """
    resume = cfg.resume
    run_dir = Path(str(resume if resume else hydra_run_dir)).expanduser()
    saved = saved_config(run_dir) if run_dir.is_dir() else None
    current = OmegaConf.to_container(OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"]), resolve=True)
    if resume:
        if saved is None:
            raise ConfigError(f"resume: '{resume}' holds no checkpoint (allowed: a run directory with a {CHECKPOINT_DIR}/ folder)")
        for key in IGNORED_ON_RESUME:
            if key in current:
                saved[key] = current[key]
        cfg = OmegaConf.create(saved)
    validate_config(cfg)
    check_output_dir(run_dir)
    if saved is not None and not resume:
        before, now = _flatten({k: v for k, v in saved.items() if k not in IGNORED_ON_RESUME}), _flatten({k: v for k, v in current.items() if k not in IGNORED_ON_RESUME})
        for key in sorted(set(before) | set(now)):
            if before.get(key, "<absent>") != now.get(key, "<absent>"):
                raise ConfigError(
                    f"{key}: {now.get(key, '<absent>')!r} differs from {before.get(key, '<absent>')!r} in the checkpoint of {run_dir} "
                    "(allowed: the run's own config to resume it, or another hydra.run.dir)"
                )
    return cfg, run_dir
