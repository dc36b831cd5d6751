"""CEM-RL's iteration of generations (Pourchot and Sigaud, ICLR 2019; the authors' ``es_grad.py``), with the
replay buffers it writes to as a choice: CEM-RL's one buffer, or ES-TD3Buffers' good, bad and
noisy buffers routed by return (Section 3.1)."""
from __future__ import annotations

from collections.abc import Callable

import torch

from torchrl_esrl.es.cem import cem_rl_gradient_steps

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


def cem_rl_iteration(cem, td3, buffer, population_collector, counters: dict, frames_per_iteration: int, start_frames: int, rl_members: int, tau: float, route: Callable = one_buffer) -> dict:
    """Generations until ``frames_per_iteration`` new frames. Each: sample a population; past
    ``start_frames`` frames and once the buffer is ready, train its first ``rl_members`` with
    the shared critic (:func:`~torchrl_esrl.es.cem.cem_rl_gradient_steps`, F = the previous
    generation's frames); every member plays one deterministic episode, written by ``route``;
    the elites update the CEM. ``counters`` (``frames``, ``last_generation_frames``,
    ``actor_steps``, 0 until set; checkpointed with the run) advance once the iteration is done. Returns the iteration's member
    returns and critic losses."""
    advanced = {"frames": 0, "last_generation_frames": 0, "actor_steps": 0, **counters}
    frames, iteration_frames, returns, critic_losses = advanced["frames"], 0, [], []
    while iteration_frames < frames_per_iteration:
        population = cem.ask()
        if frames + iteration_frames > start_frames and buffer.ready() and rl_members > 0:
            steps = cem_rl_gradient_steps(td3, buffer, population, rl_members, advanced["last_generation_frames"], tau)
            critic_losses += steps["critic_losses"]
            advanced["actor_steps"] += steps["actor_steps"]
        generation = population_collector.evaluate(population)
        route(generation, buffer)
        cem.tell(population, generation.returns)
        advanced["last_generation_frames"] = generation.frames
        iteration_frames += generation.frames
        returns.append(generation.returns)
    counters.update(advanced, frames=frames + iteration_frames)
    return {"returns": torch.cat(returns), "critic_losses": critic_losses}


def cem_rl_metrics(cem, td3, counters: dict, stats: dict) -> dict:
    """An iteration's ``metrics.csv`` columns beside the evaluation."""
    returns, critic_losses = stats["returns"], stats["critic_losses"]
    return {
        "generations": cem.generation,
        "td3_updates": td3.updates,
        "actor_steps": counters["actor_steps"],
        "population_mean_return": returns.mean().item(),
        "population_max_return": returns.max().item(),
        "critic_loss": sum(critic_losses) / len(critic_losses) if critic_losses else "",
        "cem_mean_std": cem.var.sqrt().mean().item(),
    }
