"""Good/bad routing of ES trajectories (paper, Sections 3.1 and 3.3, Algorithm 1).

An ES trajectory whose episode return reaches the threshold goes to the ``good`` buffer,
otherwise to ``bad``. The paper's threshold is ``0.9 x best return seen``; for a negative
best that value lies *above* the best, so even the best episode would be "bad". We use the
sign-safe form

    threshold = best - (1 - fraction) * |best|

which equals ``fraction x best`` for a positive best and stays below the best for a negative
one. ``observe`` updates the best *before* the comparison, so the best episode always counts
as good (see docs/deviations.md).
"""
from __future__ import annotations

import math
from collections.abc import Iterable

import torch


class Threshold:
    """Tracks the best episode return seen (ES offspring and TD3 episodes) and the routing threshold."""

    def __init__(self, fraction: float = 0.9, best: float = -math.inf):
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"threshold.fraction must be in [0, 1], got {fraction}")
        self.fraction = float(fraction)
        self.best = float(best)

    @property
    def value(self) -> float:
        """Current threshold (``-inf`` until a return has been observed)."""
        if math.isinf(self.best):
            return self.best
        return self.best - (1.0 - self.fraction) * abs(self.best)

    def observe(self, episode_return: float) -> None:
        """Update the best return (Algorithm 1: ``if F > Threshold: Threshold <- F``)."""
        episode_return = float(episode_return)
        if episode_return > self.best:
            self.best = episode_return

    def is_good(self, episode_return: float) -> bool:
        """Observe ``episode_return``, then say whether it reaches the threshold."""
        self.observe(episode_return)
        return float(episode_return) >= self.value

    def route(self, episode_returns: Iterable[float] | torch.Tensor) -> torch.Tensor:
        """Route a generation's returns in order, as Algorithm 1 does offspring by offspring.

        Returns a bool tensor: True where the trajectory goes to ``good``.
        """
        returns = torch.as_tensor(episode_returns, dtype=torch.float64).reshape(-1)
        return torch.tensor([self.is_good(r) for r in returns.tolist()], dtype=torch.bool)

    def metrics(self) -> dict[str, float]:
        """The best return and the threshold, for ``metrics.csv``."""
        return {"best_return": self.best, "threshold": self.value}

    def state_dict(self) -> dict:
        return {"fraction": self.fraction, "best": self.best}

    def load_state_dict(self, state: dict) -> None:
        self.fraction = float(state["fraction"])
        self.best = float(state["best"])

    def __repr__(self) -> str:
        return f"Threshold(fraction={self.fraction}, best={self.best:.3f}, value={self.value:.3f})"


def make_threshold(cfg) -> Threshold:
    """The threshold of the ``threshold`` section."""
    return Threshold(fraction=cfg.threshold.fraction)
