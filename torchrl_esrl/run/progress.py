"""Where a run's outer loop stands: the part of the loop state that is no component's own."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import torch

from torchrl_esrl.algorithm.td3_phase import PhaseProgress


@dataclass
class RunProgress:
    """Position of the outer loop (what a recipe's local counters would be), checkpointed."""

    iteration: int = 0  # next iteration to run
    td3_frames: int = 0  # TD3 frames of the finished iterations
    td3_phase: PhaseProgress = field(default_factory=PhaseProgress)
    counters: dict[str, int] = field(default_factory=dict)  # a recipe's own running counts
    # A recipe's own state between iteration boundaries, set before ``Run.start``: an object with
    # state_dict, load_state_dict, ``work`` (a count that grows with every step it takes) and
    # ``position()`` (where it stands, in words).
    phase: Any = None
    # The returns of the iteration's evaluations so far (per-iteration stream): a run resumed from a
    # checkpoint taken after some is given them again instead of playing them anew (Run.evaluate).
    evaluations: list[float] = field(default_factory=list)
    evaluations_given: int = 0  # of them, how many this process has given (not saved: 0 after a restore)
    started: float = field(default_factory=time.perf_counter)  # wall clock, shifted by the time before a resume

    def wall_time(self) -> float:
        return time.perf_counter() - self.started

    @property
    def frames_now(self) -> int:
        return self.td3_frames + self.td3_phase.collected

    @property
    def checkpoint_step(self) -> int:
        """The number of a checkpoint taken now: grows with every iteration, frame and phase step."""
        return self.frames_now + self.iteration + (self.phase.work if self.phase is not None else 0)

    def recorded_evaluation(self) -> float | None:
        """The next of the iteration's recorded evaluations this process has not given yet, or None."""
        if self.evaluations_given >= len(self.evaluations):
            return None
        self.evaluations_given += 1
        return self.evaluations[self.evaluations_given - 1]

    def record_evaluation(self, value: float) -> None:
        self.evaluations.append(value)
        self.evaluations_given = len(self.evaluations)

    def finish_iteration(self) -> None:
        self.iteration += 1
        self.td3_frames = self.frames_now
        self.td3_phase = PhaseProgress()
        self.evaluations, self.evaluations_given = [], 0

    def state_dict(self) -> dict:
        state = {"iteration": self.iteration, "td3_frames": self.td3_frames, "elapsed_s": self.wall_time(), "td3_phase": self.td3_phase.state_dict(), "counters": dict(self.counters),
                 "evaluations": torch.tensor(self.evaluations, dtype=torch.float64)}
        if self.phase is not None:
            state["phase"] = self.phase.state_dict()
        return state

    def load_state_dict(self, state: dict) -> None:
        self.iteration, self.td3_frames = int(state["iteration"]), int(state["td3_frames"])
        self.started = time.perf_counter() - float(state["elapsed_s"])
        self.td3_phase.load_state_dict(state["td3_phase"])
        self.counters = {key: int(value) for key, value in state["counters"].items()}
        self.evaluations = torch.as_tensor(state.get("evaluations", [])).tolist()  # none in a checkpoint from before they were kept
        if self.phase is not None and "phase" in state:  # a checkpoint from before phases were saved: at an iteration boundary
            self.phase.load_state_dict(state["phase"])
