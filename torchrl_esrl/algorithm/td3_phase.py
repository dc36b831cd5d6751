"""Algorithm 1's TD3 step: act for M frames with exploration noise, every transition into the
``noisy`` buffer, one TD3 update per frame once the buffers are ready (paper, Section 3.3)."""
from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase

from torchrl_esrl.threads import torch_threads
from torchrl_esrl.collectors.td3_collector import finished_episode_returns


@dataclass
class PhaseProgress:
    """How far one TD3 phase (Algorithm 1, "for M frames") has got; :func:`td3_phase` resumes it."""

    collected: int = 0
    updates: int = 0
    episodes: int = 0
    owed: float = 0.0
    losses: dict[str, list[float]] = field(default_factory=dict)

    def state_dict(self) -> dict:
        # Losses as float64 tensors: exact for Python floats and compact in TensorDict files.
        return {
            "collected": self.collected,
            "updates": self.updates,
            "episodes": self.episodes,
            "owed": self.owed,
            "losses": {k: torch.tensor(v, dtype=torch.float64) for k, v in self.losses.items()},
        }

    def load_state_dict(self, state: dict) -> None:
        self.collected, self.updates, self.episodes = int(state["collected"]), int(state["updates"]), int(state["episodes"])
        self.owed = float(state["owed"])
        self.losses = {k: torch.as_tensor(v).tolist() for k, v in state["losses"].items()}


def td3_phase(
    frames: int,
    frame_batches: Iterator[TensorDictBase],
    td3,
    buffer,
    on_episode: Callable[[float], None] | None = None,
    updates_per_frame: float = 1.0,
    on_batch: Callable[[int, dict], None] | None = None,
    progress=None,
) -> dict[str, float]:
    """Act for ``frames`` frames, writing to ``buffer``'s noisy part and learning once it is ready.

    ``frame_batches`` iterates over a TD3 collector's batches of frames (:func:`~torchrl_esrl.collectors.td3_collector.make_frame_batches`,
    kept alive across phases so episodes continue where they stopped). The phase runs on
    ``td3.num_threads`` torch threads. ``buffer`` is a :class:`~torchrl_esrl.data.multibuffer.MultiBuffer`
    (written under ``"noisy"``) or any TorchRL replay buffer. ``on_episode`` sees each finished
    training episode's return (Algorithm 1 lets them raise the threshold). ``progress`` (a
    :class:`PhaseProgress`) holds the phase's counters: pass the one
    restored from a checkpoint to finish a phase interrupted mid-way.
    """
    p = PhaseProgress() if progress is None else progress
    with torch_threads(td3.num_threads):  # default: this job's share of the cores (torchrl_esrl/threads.py)
        is_multibuffer = hasattr(buffer, "ready")
        ready = False  # the phase only adds items: once ready, the buffer stays ready (checked once, not per frame)
        while p.collected < frames:
            batch = next(frame_batches)
            p.collected += batch.numel()
            if is_multibuffer:
                buffer.extend(batch, "noisy")
            else:
                buffer.extend(batch)
            for episode_return in finished_episode_returns(batch):
                p.episodes += 1
                if on_episode is not None:
                    on_episode(episode_return)
            ready = ready or (buffer.ready() if is_multibuffer else len(buffer) > 0)
            if ready:
                p.owed += batch.numel() * updates_per_frame  # fractional updates carried between batches
                while p.owed >= 1:
                    p.owed -= 1
                    for key, value in td3.update(buffer.sample()).items():
                        p.losses.setdefault(key, []).append(value)
                    p.updates += 1
            if on_batch is not None:
                on_batch(batch.numel(), {"updates": p.updates, "episodes": p.episodes})
    stats = {"updates": p.updates, "episodes": p.episodes, "frames": p.collected, "critic_loss": "", "actor_loss": ""}  # "": no update yet
    stats.update({key: sum(v) / len(v) for key, v in p.losses.items()})
    return stats
