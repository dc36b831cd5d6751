"""The run harness every recipe shares: seeding, run directory, metrics, evaluation, summary.

One evaluation protocol for all algorithms (ES-TD3Buffers, TD3, OpenAI-ES, CEM-RL):

- at every iteration checkpoint (one iteration = ``td3.frames_per_iteration`` frames of the RL
  learner), the policy the algorithm *returns* is evaluated deterministically over
  ``eval.episodes`` episodes, on its own seed stream, and written to ``metrics.csv`` as
  ``eval_return`` next to the core columns :data:`CORE_COLUMNS`;
- at the end, the returned policy is evaluated over ``eval.final_episodes`` episodes and
  ``summary.json`` records it as ``final_return`` with ``algorithm``, ``env`` and ``seed``. These
  episodes have a seed stream of their own (:func:`final_episode_seeds`, a function of the run's
  seed only): they never repeat the per-iteration episodes, and every policy a run reports at
  the end (ES-TD3Buffers: the ES mean and the TD3 actor) plays the same final episodes.

Evaluation frames are counted in neither ``td3_frames`` nor ``es_frames``.
"""
from __future__ import annotations

import functools
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import hydra
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from torchrl_esrl.errors import ConfigError
from torchrl_esrl.run.config import validate_config
from torchrl_esrl.envs import quiet_logs
from torchrl_esrl.collectors.es_collector import ESCollector
from torchrl_esrl.run.factories import seed_everything
from torchrl_esrl.run.metrics import CORE_COLUMNS, MetricsLog, write_json
from torchrl_esrl.run.schema import run_cli


def final_episode_seeds(seed: int, episodes: int) -> list[int]:
    """Reset seeds of the final evaluation: a stream keyed by ``(seed, "final")``, apart from the
    per-iteration evaluation stream (``seed + 1000``) and from every training stream."""
    return np.random.default_rng([int(seed), 0x46494E]).integers(0, 2**31 - 1, size=int(episodes)).tolist()


class RunHarness:
    """What every recipe does around its algorithm.

    Args:
        cfg: the Hydra config (reads ``seed``, ``env``, ``eval``, ``logger``, ``experiment_name``,
            ``td3.frames_per_iteration``).
        run_dir: the Hydra run directory.
        algorithm: name written to ``summary.json`` (the report groups runs by it).
        columns: the recipe's own ``metrics.csv`` columns, after :data:`CORE_COLUMNS`.
        clock: seconds since the run started (a resumable clock survives a restart); by default
            the time since this harness was built.
    """

    def __init__(self, cfg: DictConfig, run_dir: str | Path, algorithm: str, columns: Sequence[str] = (), clock: Callable[[], float] | None = None):
        quiet_logs()
        seed_everything(cfg.seed)
        self.cfg = cfg
        self.algorithm = algorithm
        self.run_dir = Path(run_dir)
        start = time.perf_counter()
        self.clock = clock or (lambda: time.perf_counter() - start)
        extra = [c for c in columns if c not in CORE_COLUMNS]
        self.log_ = MetricsLog(self.run_dir, backend=cfg.logger.backend, experiment_name=cfg.experiment_name, columns=(*CORE_COLUMNS, *extra))
        self.evaluator: ESCollector | None = None
        self.last_row: dict = {}

    @property
    def wall_time_s(self) -> float:
        return round(self.clock(), 2)

    def attach_actor(self, actor) -> None:
        """Build the evaluator for ``actor``'s architecture (its own episode-seed stream)."""
        cfg = self.cfg
        self.evaluator = ESCollector(cfg.env.id, actor, backend="gym", max_episode_steps=cfg.env.max_episode_steps, seed=int(cfg.seed) + 1000)

    def evaluate(self, vector: torch.Tensor, episodes: int | None = None, seeds: Sequence[int] | None = None) -> float:
        """Mean return of the deterministic actor with flat parameters ``vector`` (episode seeds
        from the per-iteration stream unless ``seeds`` are given)."""
        if self.evaluator is None:
            raise RuntimeError("RunHarness.attach_actor must be called before evaluate")
        episodes = len(seeds) if seeds is not None else int(episodes or self.cfg.eval.episodes)
        return self.evaluator.evaluate_policy(vector.detach(), episodes, seeds=seeds).returns.mean().item()

    def evaluate_final(self, vector: torch.Tensor) -> float:
        """Mean return over the ``eval.final_episodes`` episodes of the final evaluation's own stream."""
        return self.evaluate(vector, seeds=final_episode_seeds(self.cfg.seed, self.cfg.eval.final_episodes))

    def log(self, iteration: int, td3_frames: int, es_frames: int, eval_return: float, **extra) -> dict:
        """One checkpoint row of ``metrics.csv`` (and of the TorchRL logger)."""
        row = {
            "iteration": iteration,
            "td3_frames": int(td3_frames),
            "es_frames": int(es_frames),
            "total_frames": int(td3_frames) + int(es_frames),
            "eval_return": eval_return,
            "wall_time_s": self.wall_time_s,
            **extra,
        }
        self.log_.log(row)
        self.last_row = row
        return row

    def finish(self, returned: torch.Tensor, extra: Mapping | None = None, alias: str | None = None) -> dict:
        """Final evaluation of the returned policy; writes and returns ``summary.json``.

        ``alias`` also stores ``final_return`` under a recipe-specific name."""
        cfg = self.cfg
        summary = {
            "algorithm": self.algorithm,
            "env": cfg.env.id,
            "env_name": cfg.env.name,
            "seed": int(cfg.seed),
            "experiment": cfg.experiment_name,
            "iterations": int(cfg.iterations),
            "frames_per_iteration": int(cfg.td3.frames_per_iteration),
            "td3_frames": self.last_row.get("td3_frames", 0),
            "es_frames": self.last_row.get("es_frames", 0),
            "final_return": self.evaluate_final(returned),
            "final_episodes": int(cfg.eval.final_episodes),
            **dict(extra or {}),
        }
        if alias:
            summary[alias] = summary["final_return"]
        summary["wall_time_s"] = self.wall_time_s
        write_json(self.run_dir / "summary.json", summary)
        return summary


CONF_DIR = Path(__file__).resolve().parents[2] / "conf"


def hydra_main(train: Callable[[DictConfig, Path], dict], config_name: str) -> Callable[[], None]:
    """The ``main`` of a baseline recipe: Hydra config ``conf/<config_name>.yaml``, fail-fast
    validation, then ``train(cfg, run_dir)`` in the Hydra run directory. Called through
    :func:`~torchrl_esrl.run.schema.run_cli`, as ``recipes/es_td3.py`` is: Hydra's own config errors
    (unknown keys, wrong types) are one line too, and a numerical fault stops with one line."""

    @hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name=config_name)
    def main(cfg: DictConfig) -> None:
        try:
            validate_config(cfg)
        except ConfigError as error:
            raise SystemExit(f"config error: {error}") from None
        run_dir = Path(HydraConfig.get().runtime.output_dir)
        if cfg.logger.progress:
            print(OmegaConf.to_yaml(cfg, resolve=True))
        try:
            summary = train(cfg, run_dir)
        except FloatingPointError as fault:
            raise SystemExit(f"numerical fault: {fault}; run stopped") from None
        print(f"{summary['algorithm']}: final return {summary['final_return']:.1f} -> {run_dir}")

    return functools.partial(run_cli, main)
