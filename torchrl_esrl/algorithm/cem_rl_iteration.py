"""CEM-RL's iteration of generations (Pourchot and Sigaud, ICLR 2019; the authors' ``es_grad.py``), with the
replay buffers it writes to as a choice: CEM-RL's one buffer, or ES-TD3Buffers' good, bad and
noisy buffers routed by return (Section 3.1)."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from torchrl_esrl.collectors.generation import population_returns
from torchrl_esrl.es.cem import GradientStepsPosition, cem_rl_gradient_steps
from torchrl_esrl.modules.networks import actor_parameters
from torchrl_esrl.run.capacity import FLOAT, Holding

# What a CEM-RL run's ``td3_frames`` count (its recipes' ``AlgorithmInfo.td3_frames``): it has no TD3 phase.
POPULATION_FRAMES = "TD3 frames are every population member's episode, the CEM's fitness evaluations and the critic's data alike (no ES frames)"


def one_buffer(generation, buffer) -> None:
    """CEM-RL: every member's episode into the one replay buffer (``noisy``)."""
    buffer.extend(generation.transitions, "noisy")


def routed_by_return(threshold, rl_members: int) -> Callable:
    """The RL members' episodes (the first ``rl_members``) to noisy, their returns raising the
    best; the CEM members' to good when their return reaches the threshold, else to bad, member
    by member as Algorithm 1 routes ES offspring."""

    def route(generation, buffer) -> None:
        returns = generation.returns
        for episode_return in returns[:rl_members].tolist():
            threshold.observe(episode_return)
        rl = torch.arange(len(returns)) < rl_members
        good = torch.zeros(len(returns), dtype=torch.bool)
        good[rl_members:] = threshold.route(returns[rl_members:])
        buffer.extend(generation.transitions[generation.member_mask(rl)], "noisy")
        buffer.extend(generation.transitions[generation.member_mask(good)], "good")
        buffer.extend(generation.transitions[generation.member_mask(~good & ~rl)], "bad")

    return route


@dataclass
class GenerationsProgress:
    """How far one iteration of generations until M new frames (CEM-RL's, the CEM's) has got;
    :func:`cem_rl_iteration` resumes it. A recipe hands it to the run as ``run.progress.phase``, so
    that it is checkpointed with the run at every stop point: the iteration's frames, member
    returns and critic losses so far, and the generation under way (its population, its gradient
    steps' position; CEM-RL's only)."""

    frames: int = 0
    returns: list[torch.Tensor] = field(default_factory=list)
    critic_losses: list[float] = field(default_factory=list)
    population: torch.Tensor | None = None  # sampled, its RL members in training; None between generations
    steps: GradientStepsPosition = field(default_factory=GradientStepsPosition)
    done: int = 0  # generations and gradient steps finished over the run

    @property
    def work(self) -> int:
        """Generations and gradient steps over the run: grows with every step (numbers the run's checkpoints)."""
        return self.done + self.steps.steps

    def position(self) -> str:
        """Where the iteration stands, in words (a stop line's)."""
        return f"frame {self.frames} of the iteration" + ("" if self.population is None else f", generation under way, {self.steps.steps} gradient steps taken")

    def finish_generation(self, frames: int, returns: torch.Tensor) -> None:
        self.frames += frames
        self.returns.append(returns)
        self.critic_losses += self.steps.critic_losses
        self.done += 1 + self.steps.steps
        self.population, self.steps = None, GradientStepsPosition()

    def finish_iteration(self) -> dict:
        """The iteration's member returns (empty if it played no generation) and critic losses; the
        next iteration starts from here."""
        stats = {"returns": torch.cat(self.returns) if self.returns else torch.empty(0), "critic_losses": self.critic_losses}
        self.frames, self.returns, self.critic_losses = 0, [], []
        return stats

    def state_dict(self) -> dict:
        returns = torch.cat(self.returns) if self.returns else torch.empty(0)
        population = self.population if self.population is not None else torch.empty(0)
        return {"frames": self.frames, "done": self.done, "returns": returns, "critic_losses": torch.tensor(self.critic_losses, dtype=torch.float64),
                "population": population, "steps": self.steps.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.frames, self.done = int(state["frames"]), int(state["done"])
        returns, population = torch.as_tensor(state["returns"]), torch.as_tensor(state["population"])
        self.returns = [returns.clone()] if returns.numel() else []
        self.critic_losses = torch.as_tensor(state["critic_losses"]).tolist()
        self.population = population.clone() if population.numel() else None
        self.steps = GradientStepsPosition()
        self.steps.load_state_dict(state["steps"])


def cem_rl_iteration(cem, td3, buffer, population_collector, counters: dict, frames_per_iteration: int, start_frames: int, rl_members: int, tau: float,
                     route: Callable = one_buffer, at: GenerationsProgress | None = None, stop_point: Callable[[str | Callable[[], str]], None] | None = None) -> dict:
    """Generations until ``frames_per_iteration`` new frames. Each: sample a population; past
    ``start_frames`` frames and once the buffer is ready, train its first ``rl_members`` with
    the shared critic (:func:`~torchrl_esrl.es.cem.cem_rl_gradient_steps`, F = the previous
    generation's frames); every member plays one deterministic episode, written by ``route``;
    the elites update the CEM. ``counters`` (``frames``, ``last_generation_frames``,
    ``actor_steps``, 0 until set; checkpointed with the run) advance generation by generation.
    Returns the iteration's member returns and critic losses.

    ``at``: where the iteration stands (default: at its start), advanced as it goes;
    ``stop_point(where)`` is called after every gradient step and every generation, where the
    run's state is whole (a stop there checkpoints that point and resumes from it); ``where``
    is the point in words, or within the gradient steps a function giving them.
    """
    at = GenerationsProgress() if at is None else at
    for key in ("frames", "last_generation_frames", "actor_steps"):
        counters.setdefault(key, 0)
    while at.frames < frames_per_iteration:
        if at.population is None:
            population = cem.ask()
            learning = counters["frames"] > start_frames and buffer.ready() and rl_members > 0
        else:  # stopped within its gradient steps: the same population, learning
            population, learning = at.population, True
        if learning:
            at.population = population
            where = lambda: f"in CEM-RL's gradient steps, member {at.steps.member + 1}/{rl_members}"  # worded only on a stop
            on_step = None if stop_point is None else (lambda: stop_point(where))
            steps = cem_rl_gradient_steps(td3, buffer, population, rl_members, counters["last_generation_frames"], tau, at.steps, on_step)
            counters["actor_steps"] += steps["actor_steps"]
        generation = population_collector.evaluate(population)
        route(generation, buffer)
        cem.tell(population, generation.returns)
        counters["last_generation_frames"] = generation.frames
        counters["frames"] += generation.frames
        at.finish_generation(generation.frames, generation.returns)
        if stop_point is not None:
            stop_point(f"after CEM-RL generation {cem.generation}")
    return at.finish_iteration()


def cem_rl_metrics(cem, td3, counters: dict, stats: dict) -> dict:
    """An iteration's ``metrics.csv`` columns beside the evaluation."""
    returns, critic_losses = stats["returns"], stats["critic_losses"]
    return {
        "generations": cem.generation,
        "td3_updates": td3.updates,
        "actor_steps": counters["actor_steps"],
        **population_returns(returns),
        "critic_loss": sum(critic_losses) / len(critic_losses) if critic_losses else "",
        "cem_mean_std": cem.var.sqrt().mean().item(),
    }


def population_under_way_holdings(cfg, sizes) -> list[Holding]:
    """What a stop within a CEM-RL generation's gradient steps adds to the checkpoint: its
    population (:attr:`GenerationsProgress.population`), a copy of what memory already holds."""
    return [Holding("population", FLOAT * actor_parameters(cfg, sizes) * int(cfg.cem.population_size), "cem.population_size", in_memory=False)]
