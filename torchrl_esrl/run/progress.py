"""Where a run's outer loop stands: the part of the loop state that is no component's own."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

from torchrl_esrl.algorithm.td3_phase import PhaseProgress


@dataclass
class RunProgress:
    """Position of the outer loop (what a recipe's local counters would be), checkpointed."""

    iteration: int = 0  # next iteration to run
    td3_frames: int = 0  # TD3 frames of the finished iterations
    td3_phase: PhaseProgress = field(default_factory=PhaseProgress)
    counters: dict[str, int] = field(default_factory=dict)  # a recipe's own running counts
    started: float = field(default_factory=time.perf_counter)  # wall clock, shifted by the time before a resume

    def wall_time(self) -> float:
        return time.perf_counter() - self.started

    @property
    def frames_now(self) -> int:
        return self.td3_frames + self.td3_phase.collected

    def finish_iteration(self) -> None:
        self.iteration += 1
        self.td3_frames = self.frames_now
        self.td3_phase = PhaseProgress()

    def state_dict(self) -> dict:
        return {"iteration": self.iteration, "td3_frames": self.td3_frames, "elapsed_s": self.wall_time(), "td3_phase": self.td3_phase.state_dict(), "counters": dict(self.counters)}

    def load_state_dict(self, state: dict) -> None:
        self.iteration, self.td3_frames = int(state["iteration"]), int(state["td3_frames"])
        self.started = time.perf_counter() - float(state["elapsed_s"])
        self.td3_phase.load_state_dict(state["td3_phase"])
        self.counters = {key: int(value) for key, value in state["counters"].items()}
