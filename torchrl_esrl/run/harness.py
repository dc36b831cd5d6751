"""The run harness every recipe shares: seeding, run directory, metrics, evaluation, summary.

One evaluation protocol for every recipe:

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

import logging
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from torchrl_esrl.envs import quiet_logs
from torchrl_esrl.errors import error_line
from torchrl_esrl.collectors.es_collector import ESCollector, make_evaluator
from torchrl_esrl.modules.networks import flat_parameters
from torchrl_esrl.run.algorithm_info import AlgorithmInfo
from torchrl_esrl.run.plot import plot_run
from torchrl_esrl.run.console import returns_text
from torchrl_esrl.run.determinism import seed_everything
from torchrl_esrl.run.metrics import MetricsLog, write_json


log = logging.getLogger(__name__)  # under torchrl_esrl.run: the run directory's <recipe>.log only


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
        algorithm: what the recipe runs (:class:`~torchrl_esrl.run.algorithm_info.AlgorithmInfo`;
            a bare name is its own label); its name goes into ``summary.json`` (the report groups
            runs by it).
        clock: seconds since the run started (a resumable clock survives a restart); by default
            the time since this harness was built.
    """

    def __init__(self, cfg: DictConfig, run_dir: str | Path, algorithm: AlgorithmInfo | str, clock: Callable[[], float] | None = None):
        quiet_logs()
        seed_everything(cfg.seed)
        self.cfg = cfg
        self.info = algorithm if isinstance(algorithm, AlgorithmInfo) else AlgorithmInfo(algorithm, algorithm, "returned policy")
        self.algorithm = self.info.name
        self.run_dir = Path(run_dir)
        start = time.perf_counter()
        self.clock = clock or (lambda: time.perf_counter() - start)
        self.log_ = MetricsLog(self.run_dir, backend=cfg.logger.backend, experiment_name=cfg.experiment_name)
        self.evaluator: ESCollector | None = None
        self.initial_return: float | None = None  # set by attach_actor
        self.bar = None  # the progress bar, set by Run.iterations
        self.returns_text = ""  # the last evaluation, shown on the bar
        self.last_row: dict = {}
        self.threads: dict[str, int] = {}  # the phases' thread counts (Run.start), for summary.json
        self.pieces: dict[str, str] = {}  # what computes each piece of the run (Run.start), for summary.json

    @property
    def wall_time_s(self) -> float:
        return round(self.clock(), 2)

    def attach_actor(self, actor) -> None:
        """Build the evaluator for ``actor``'s architecture (its own episode-seed stream), and
        evaluate ``actor`` as built, before any training, with the protocol of the final evaluation
        (the same ``eval.final_episodes`` episodes): ``initial_return`` in ``summary.json``, the
        baseline the returned policy is compared with. The per-iteration evaluation stream is not
        drawn from."""
        cfg = self.cfg
        self.evaluator = make_evaluator(cfg, actor)
        self.initial_return = self.evaluate_final(flat_parameters(actor))

    def evaluate(self, vector: torch.Tensor, episodes: int | None = None, seeds: Sequence[int] | None = None) -> float:
        """Mean return of the deterministic actor with flat parameters ``vector`` (episode seeds
        from the per-iteration stream unless ``seeds`` are given)."""
        if self.evaluator is None:
            raise RuntimeError("RunHarness.attach_actor must be called before evaluate")
        episodes = len(seeds) if seeds is not None else int(episodes or self.cfg.eval.episodes)
        return self.evaluator.evaluate_policy(vector.detach().cpu(), episodes, seeds=seeds).returns.mean().item()

    def evaluate_final(self, vector: torch.Tensor) -> float:
        """Mean return over the ``eval.final_episodes`` episodes of the final evaluation's own stream."""
        return self.evaluate(vector, seeds=final_episode_seeds(self.cfg.seed, self.cfg.eval.final_episodes))

    def log(self, iteration: int, td3_frames: int, es_frames: int, eval_return: float, **extra) -> dict:
        """One row of ``metrics.csv`` (and of the TorchRL logger): the core columns, then ``extra``
        (each component's ``metrics()``)."""
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
        self.returns_text = returns_text(row, self.initial_return)
        self.show_phase("evaluated")
        return row

    def show_phase(self, phase: str) -> None:
        """The progress bar's text: the phase under way and the last evaluation's returns."""
        if self.bar is not None:
            self.bar.set_postfix_str(f"{phase}; {self.returns_text}" if self.returns_text else phase)

    def finish(self, returned: torch.Tensor, extra: Mapping | None = None, alias: str | None = None) -> dict:
        """Final evaluation of the returned policy; draws ``learning_curve.png`` (a figure that fails
        costs itself and one warning line, never the summary); writes and returns ``summary.json``,
        the last file a run writes (its presence marks the run finished: a rerun leaves it alone).

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
        summary["initial_return"] = self.initial_return
        if self.threads:
            summary["threads"] = self.threads
        if self.pieces:
            summary["pieces"] = self.pieces
        summary["wall_time_s"] = self.wall_time_s
        try:
            plot_run(self.run_dir, summary, info=self.info)  # learning_curve.png
        except Exception as error:  # noqa: BLE001 - a figure that fails costs itself, never the summary
            warning = f"warning: learning_curve.png was not drawn ({error_line(error)}); the run's results are in summary.json and metrics.csv"
            log.warning(warning)
            print(warning, file=sys.stderr, flush=True)
        write_json(self.run_dir / "summary.json", summary)  # last, atomically: a run with a summary has finished
        return summary
