"""The overwrite rule (paper, Section 3.2 and the end of Algorithm 1).

After each iteration the TD3 actor and the ES mean are evaluated. If TD3's evaluation,
averaged over the last ``window`` iterations, beats the ES mean's average over the same
iterations, the ES mean becomes the TD3 actor's parameters. Averages damp the occasional
collapse of either learner between updates, as the paper describes.

``mode="soft"`` is the fix Section 5 proposes for the variance hard overwrites cause: when the
rule fires, the mean moves only part-way, ``mean <- (1 - mix) * mean + mix * td3_actor``
(:meth:`OpenES.set_mean` with ``mix``); ``mode="hard"`` is ``mix = 1``, Algorithm 1.
"""
from __future__ import annotations

from collections import deque
from dataclasses import asdict, dataclass


@dataclass
class OverwriteDecision:
    iteration: int
    td3_return: float
    es_return: float
    td3_average: float
    es_average: float
    overwrite: bool

    def as_dict(self) -> dict:
        return asdict(self)

    def metrics(self) -> dict:
        """Both evaluations, their averages and the decision, for ``metrics.csv``."""
        return {"td3_eval_return": self.td3_return, "es_eval_return": self.es_return, "td3_average": self.td3_average, "es_average": self.es_average, "overwritten": self.overwrite}


class OverwriteRule:
    """Decides, once per iteration, whether the ES mean is recentred on the TD3 actor, and by how
    much: :attr:`mix` is the share of the TD3 actor in the new mean (1 for a hard overwrite)."""

    def __init__(self, window: int, mode: str, mix: float):
        if window < 1:
            raise ValueError(f"overwrite.window must be >= 1, got {window}")
        if mode not in ("hard", "soft") or not 0 < mix <= 1:
            raise ValueError(f"overwrite.mode must be hard or soft and overwrite.mix in (0, 1], got {mode!r}, {mix}")
        self.window = int(window)
        self.mode = mode
        self.mix = 1.0 if mode == "hard" else float(mix)
        self.td3_returns: deque[float] = deque(maxlen=self.window)
        self.es_returns: deque[float] = deque(maxlen=self.window)
        self.decisions: list[OverwriteDecision] = []

    def __call__(self, td3_return: float, es_return: float) -> OverwriteDecision:
        self.td3_returns.append(float(td3_return))
        self.es_returns.append(float(es_return))
        td3_average = sum(self.td3_returns) / len(self.td3_returns)
        es_average = sum(self.es_returns) / len(self.es_returns)
        decision = OverwriteDecision(
            iteration=len(self.decisions),
            td3_return=float(td3_return),
            es_return=float(es_return),
            td3_average=td3_average,
            es_average=es_average,
            overwrite=td3_average > es_average,
        )
        self.decisions.append(decision)
        return decision

    def mean_return(self, decision: OverwriteDecision, evaluate_mean) -> float:
        """The return of the ES mean after ``decision``, the policy the run returns: the ES evaluation
        where the mean was kept, the TD3 one after a hard overwrite (the mean is the TD3 actor), and
        ``evaluate_mean()``, a new evaluation, after a soft one."""
        if not decision.overwrite:
            return decision.es_return
        return decision.td3_return if self.mix == 1 else evaluate_mean()

    def state_dict(self) -> dict:
        return {
            "window": self.window,
            "td3_returns": list(self.td3_returns),
            "es_returns": list(self.es_returns),
            "decisions": [d.as_dict() for d in self.decisions],
        }

    def load_state_dict(self, state: dict) -> None:
        self.window = int(state["window"])
        self.td3_returns = deque(state["td3_returns"], maxlen=self.window)
        self.es_returns = deque(state["es_returns"], maxlen=self.window)
        self.decisions = [OverwriteDecision(**d) for d in state["decisions"]]


def make_overwrite_rule(cfg) -> OverwriteRule:
    """The overwrite rule of the ``overwrite`` section."""
    return OverwriteRule(window=cfg.overwrite.window, mode=cfg.overwrite.mode, mix=cfg.overwrite.mix)
