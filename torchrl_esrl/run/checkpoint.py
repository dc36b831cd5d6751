"""The checkpoint of a run: everything the rest of the run depends on, so that a run killed at
any moment and resumed from its last checkpoint writes the same ``metrics.csv`` as a run never
interrupted (``wall_time_s`` excepted). What ES-TD3Buffers saves (the baselines save the
subset they have):

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
- the loop position (:class:`~torchrl_esrl.run.progress.RunProgress`: iteration, TD3 frames,
  the TD3 phase in progress) and the logger's position
  (:class:`~torchrl_esrl.run.logger_position.LoggerPosition`).

Files are written by TorchRL's :class:`~torchrl.checkpoint.Checkpoint` (staged in a hidden
directory, then renamed) under :class:`~torchrl.checkpoint.CheckpointRotation`
(``<run_dir>/checkpoints/checkpoint-<td3 frames + iteration>``, ``checkpoint.keep_last`` kept), so a
kill during a save leaves the previous checkpoint whole. Checkpoints are taken at every
iteration boundary and every ``checkpoint.every_frames`` TD3 frames (mid-phase, possibly
mid-episode); :meth:`RunCheckpoint.save` refuses to write non-finite parameters, so nothing
is saved after a numerical fault.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import torch
from torchrl.checkpoint import Checkpoint, CheckpointRotation, GlobalRNGState, StateDictCheckpointAdapter

from torchrl_esrl.data.multibuffer import MultiBuffer
from torchrl_esrl.run.logger_position import LoggerPosition
from torchrl_esrl.run.progress import RunProgress

CHECKPOINT_DIR = "checkpoints"


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
        config: the resolved config as a plain dict (saved; compared on resume, see resume.py).
        every_frames: also save every this many TD3 frames (0: iteration boundaries only).
        components: name -> object with ``state_dict``/``load_state_dict``.
    """

    def __init__(self, run_dir: str | Path, config: dict, every_frames: int, keep_last: int, **components):
        self.run_dir = Path(run_dir)
        self.every_frames = int(every_frames)
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
        self._remove_dead_stages()
        path = self.latest() if path is None else Path(path)
        if path is None:
            return None
        self.checkpoint.load(path)
        self._last_frames = self.progress.frames_now
        return path

    def _remove_dead_stages(self) -> None:
        """A save killed midway leaves its hidden staging folder (TorchRL removes one only on an
        exception). One run writes here at a time, so any found before it starts are dead."""
        for stage in (self.run_dir / CHECKPOINT_DIR).glob(".*.stage-*"):
            shutil.rmtree(stage, ignore_errors=True)


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
