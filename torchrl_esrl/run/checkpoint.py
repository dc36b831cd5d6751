"""Runs that survive: checkpoints and exact resume of Algorithm 1 (issue #5).

A checkpoint holds everything the rest of a run depends on, so that a run killed at any moment
and resumed from its last checkpoint writes the same ``metrics.csv`` as a run never
interrupted (``wall_time_s`` excepted):

- TD3: actor, twin critics, target networks, both Adam optimisers, update count
  (:meth:`TD3.state_dict`), and the exploration module;
- ES: mean, Adam state, noise generator, generation (:meth:`OpenES.state_dict`); the ES
  collector's stream of episode seeds and frame count;
- the threshold (best return), the overwrite rule's window and decision history;
- the three buffers with their contents (:meth:`MultiBuffer.state_dict`, TorchRL storages);
- the TD3 environment mid-episode (:class:`TD3EnvState`): MuJoCo's integration state
  (``mj_getState``: qpos, qvel, act, time, warm start...), gymnasium's ``np_random`` and its
  wrappers' counters (``TimeLimit`` elapsed steps...), and the TorchRL ``Collector``'s carried
  tensordict (``episode_reward`` of ``RewardSum``, ``step_count`` of ``StepCounter``,
  trajectory ids) and counters;
- the global RNGs (torch, numpy, Python: exploration noise, buffer sampling and TD3's target
  smoothing draw from torch's), TorchRL's :class:`~torchrl.checkpoint.GlobalRNGState`;
- the loop position (:class:`RunProgress`: iteration, TD3 frames, the TD3 phase in progress)
  and the logger's position (byte size of ``metrics.csv`` and of every TorchRL logger file).

Files are written by TorchRL's :class:`~torchrl.checkpoint.Checkpoint` (staged in a hidden
directory, then renamed) under :class:`~torchrl.checkpoint.CheckpointRotation`
(``<run_dir>/checkpoints/checkpoint-<td3 frames + iteration>``, the two newest kept), so a
kill during a save leaves the previous checkpoint whole. Checkpoints are taken at every
iteration boundary and every ``checkpoint.every_frames`` TD3 frames (mid-phase, possibly
mid-episode); :meth:`RunCheckpoint.save` refuses to write non-finite parameters, so nothing
is saved after a numerical fault.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torchrl.checkpoint import Checkpoint, CheckpointRotation, GlobalRNGState, StateDictCheckpointAdapter

from torchrl_esrl.algorithm.td3_phase import PhaseProgress
from torchrl_esrl.data.multibuffer import MultiBuffer

CHECKPOINT_DIR = "checkpoints"


# ----------------------------------------------------------------------------- determinism
def make_deterministic(threads: int | None = None) -> None:
    """Deterministic CPU kernels; pin the thread count (results may depend on it)."""
    torch.use_deterministic_algorithms(True, warn_only=True)
    if threads:
        torch.set_num_threads(int(threads))


# ------------------------------------------------------------------------------ loop state
@dataclass
class RunProgress:
    """Position of the outer loop of Algorithm 1 (what the recipe's local counters were)."""

    iteration: int = 0  # next iteration to run
    td3_frames: int = 0  # TD3 frames of the finished iterations
    td3_phase: PhaseProgress = field(default_factory=PhaseProgress)
    started: float = field(default_factory=time.perf_counter)  # wall clock, shifted by the time before a resume

    def wall_time(self) -> float:
        return time.perf_counter() - self.started

    @property
    def frames_now(self) -> int:
        return self.td3_frames + self.td3_phase.collected

    def finish_iteration(self, td3_frames: int) -> None:
        self.iteration += 1
        self.td3_frames = td3_frames
        self.td3_phase = PhaseProgress()

    def state_dict(self) -> dict:
        return {"iteration": self.iteration, "td3_frames": self.td3_frames, "elapsed_s": self.wall_time(), "td3_phase": self.td3_phase.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.iteration, self.td3_frames = int(state["iteration"]), int(state["td3_frames"])
        self.started = time.perf_counter() - float(state["elapsed_s"])
        self.td3_phase.load_state_dict(state["td3_phase"])


# --------------------------------------------------------------------------- the logger
class LoggerPosition:
    """Byte sizes of ``metrics.csv`` and the TorchRL logger's files; restoring truncates to them,
    so rows written after the checkpoint are written again, once, by the resumed run."""

    def __init__(self, run_dir: Path):
        self.run_dir = Path(run_dir)

    def _files(self) -> list[Path]:
        files = [self.run_dir / "metrics.csv"]
        logs = self.run_dir / "logs"
        if logs.exists():
            files += sorted(p for p in logs.rglob("*") if p.is_file())
        return [p for p in files if p.exists()]

    def state_dict(self) -> dict:
        return {"files": {str(p.relative_to(self.run_dir)): p.stat().st_size for p in self._files()}}

    def load_state_dict(self, state: dict) -> None:
        sizes = state["files"]
        for path in self._files():
            size = sizes.get(str(path.relative_to(self.run_dir)))
            if size is None:
                path.unlink()  # created after the checkpoint
            elif path.stat().st_size > size:
                os.truncate(path, size)


# ----------------------------------------------------------------------- the checkpoint
class _Value:
    """A value object with state_dict/load_state_dict (for Checkpoint's state-dict adapter)."""

    def __init__(self, get, set_):
        self._get, self._set = get, set_

    def state_dict(self):
        return self._get()

    def load_state_dict(self, state):
        self._set(state)


class RunCheckpoint:
    """Saves and restores a whole run of Algorithm 1 in ``<run_dir>/checkpoints``.

    Args:
        run_dir: the run directory (metrics.csv, logs/ and checkpoints/ live there).
        config: the resolved config as a plain dict (saved; compared on resume by the recipe).
        every_frames: also save every this many TD3 frames (0: iteration boundaries only).
        components: name -> object with ``state_dict``/``load_state_dict``.
    """

    def __init__(self, run_dir: str | Path, config: dict, every_frames: int = 0, keep_last: int = 2, **components):
        self.run_dir = Path(run_dir)
        self.every_frames = int(every_frames or 0)
        self.rotation = CheckpointRotation(self.run_dir / CHECKPOINT_DIR, keep_last=keep_last)
        self.progress: RunProgress = components["progress"]
        self.config = config
        self.components = components
        self.checkpoint = Checkpoint(
            rng=GlobalRNGState(),
            logger=LoggerPosition(self.run_dir),
            threads=_Value(lambda: {"torch": torch.get_num_threads()}, lambda s: torch.set_num_threads(int(s["torch"]))),
            **components,
        ).register_adapter(MultiBuffer, StateDictCheckpointAdapter())  # a ReplayBuffer, saved by state_dict as ever (not dump)
        self._last_frames = self.progress.frames_now

    def latest(self) -> Path | None:
        return self.rotation.latest() if (self.run_dir / CHECKPOINT_DIR).exists() else None

    def save(self) -> Path:
        """Write a checkpoint of the current state (refuses non-finite parameters)."""
        for name, component in self.components.items():
            for tensor in _parameters_of(component):
                if not torch.isfinite(tensor).all():
                    raise FloatingPointError(f"refusing to checkpoint non-finite parameters of '{name}'")
        self._last_frames = self.progress.frames_now
        step = self.progress.frames_now + self.progress.iteration  # grows with every save
        return self.rotation.save(self.checkpoint, step=step, metadata={"iteration": self.progress.iteration, "td3_frames": self.progress.frames_now, "config": self.config})

    def maybe_save_mid_phase(self, *_):
        """``td3_phase`` ``on_batch`` hook: save once every ``every_frames`` TD3 frames."""
        if self.every_frames and self.progress.frames_now // self.every_frames > self._last_frames // self.every_frames:
            self.save()

    def restore(self, path: str | Path | None = None) -> Path | None:
        """Load ``path`` (the latest checkpoint by default) into the live components; None if there is none."""
        path = self.latest() if path is None else Path(path)
        if path is None:
            return None
        self.checkpoint.load(path)
        self._last_frames = self.progress.frames_now
        return path


def saved_config(run_dir: str | Path) -> dict | None:
    """The config stored with the latest checkpoint of ``run_dir`` (None if it has none)."""
    directory = Path(run_dir) / CHECKPOINT_DIR
    if not directory.exists():
        return None
    latest = CheckpointRotation(directory, keep_last=1).latest()
    return None if latest is None else Checkpoint.manifest(latest)["metadata"]["config"]


def _parameters_of(component):
    if hasattr(component, "mean") and isinstance(getattr(component, "mean"), torch.Tensor):
        yield component.mean.detach()
    loss = getattr(component, "loss", None)
    if isinstance(loss, torch.nn.Module):
        yield from (p.detach() for p in loss.parameters())


# -------------------------------------------------------------------- resume and checks
IGNORED_ON_RESUME = ("resume", "logger", "checkpoint", "hydra")  # may change between a run and its resume


def _flatten(node, prefix: str = "") -> dict:
    if isinstance(node, dict):
        out = {}
        for key, value in node.items():
            out.update(_flatten(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: node}


def prepare_run(cfg, hydra_run_dir):
    """Every check before any work (issue #5): values, the output directory and, in a run
    directory that holds a checkpoint, that the config is the run's own.

    ``resume=<dir>`` continues ``<dir>`` with the config saved in its checkpoint (``logger``
    and ``checkpoint`` settings from the command line). Returns ``(config, run_dir)``; raises
    :class:`~torchrl_esrl.run.config.ConfigError` with a one-line message.
    """
    from omegaconf import OmegaConf

    from torchrl_esrl.errors import ConfigError
    from torchrl_esrl.run.config import check_output_dir, validate_config

    resume = cfg.get("resume")
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
