"""CEM-RL (Pourchot and Sigaud, "CEM-RL: Combining evolutionary and gradient-based methods for
policy search", ICLR 2019), the baseline of ``recipes/cem_rl.py``.

:class:`DiagonalCEM` is the cross-entropy method over the actor's flat parameters with a
diagonal covariance (their Algorithm 1): sample ``z_i ~ N(mu, diag(var))``; the top half by
return are the elites, weighted ``lambda_i ∝ log((K + 1) / i)`` for rank i of K elites;

    mu_new  = sum_i lambda_i z_i
    var_new = sum_i lambda_i (z_i - mu_old)^2 + eps,     eps <- tau eps + (1 - tau) eps_end

:func:`td3_improve_member` is the RL half: before evaluation, half of the population is loaded
into the TD3 actor (targets too), trained against the shared critic, and written back.
"""
from __future__ import annotations

import torch

from torchrl_esrl.modules.networks import flat_parameters, load_flat_parameters


def elite_weights(num_elites: int) -> torch.Tensor:
    """CEM-RL's rank weights ``log((K + 1) / i)``, i = 1..K, normalised to sum to 1."""
    ranks = torch.arange(1, num_elites + 1, dtype=torch.float64)
    weights = torch.log((num_elites + 1) / ranks)
    return (weights / weights.sum()).float()


class DiagonalCEM:
    """Cross-entropy method with a diagonal Gaussian (CEM-RL's ``sepCEM``).

    Args:
        mean: initial mean (``flat_parameters(actor)``).
        population_size: samples per generation.
        sigma_init: initial standard deviation of every coordinate (CEM-RL: 1e-3).
        elite_fraction: share of the population that updates the distribution (CEM-RL: 0.5).
        damping_init, damping_end, damping_tau: the variance floor eps added each update and its
            exponential decay (CEM-RL: 1e-3, 1e-5, 0.95).
        generator: torch RNG of the samples.
    """

    def __init__(
        self,
        mean: torch.Tensor,
        population_size: int = 10,
        sigma_init: float = 1e-3,
        elite_fraction: float = 0.5,
        damping_init: float = 1e-3,
        damping_end: float = 1e-5,
        damping_tau: float = 0.95,
        generator: torch.Generator | None = None,
    ):
        if population_size < 2:
            raise ValueError(f"cem.population_size must be >= 2, got {population_size}")
        self.mean = mean.detach().clone().float().reshape(-1)
        self.var = torch.full_like(self.mean, float(sigma_init) ** 2)
        self.population_size = int(population_size)
        self.num_elites = max(1, int(round(population_size * elite_fraction)))
        self.weights = elite_weights(self.num_elites)
        self.damping = float(damping_init)
        self.damping_end = float(damping_end)
        self.damping_tau = float(damping_tau)
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.generation = 0

    def ask(self) -> torch.Tensor:
        """Sample ``[population_size, D]`` actors from N(mean, diag(var))."""
        eps = torch.randn(self.population_size, self.mean.numel(), generator=self.generator)
        return self.mean + self.var.sqrt() * eps

    def tell(self, population: torch.Tensor, returns: torch.Tensor) -> torch.Tensor:
        """Update mean and variance from the evaluated ``population`` (as evaluated, i.e. after
        the TD3 steps of its RL half); returns the elite indices, best first."""
        returns = torch.as_tensor(returns, dtype=torch.float64).reshape(-1)
        if returns.numel() != population.shape[0]:
            raise ValueError(f"expected {population.shape[0]} returns, got {returns.numel()}")
        elites = returns.argsort(descending=True, stable=True)[: self.num_elites]
        z = population[elites].float()
        old_mean = self.mean
        self.mean = self.weights @ z
        self.var = self.weights @ (z - old_mean) ** 2 + self.damping
        self.damping = self.damping_tau * self.damping + (1 - self.damping_tau) * self.damping_end
        self.generation += 1
        return elites

    def state_dict(self) -> dict:
        return {"mean": self.mean.clone(), "var": self.var.clone(), "damping": self.damping, "generator": self.generator.get_state(), "generation": self.generation}

    def load_state_dict(self, state: dict) -> None:
        self.mean, self.var = state["mean"].clone(), state["var"].clone()
        self.damping, self.generation = float(state["damping"]), int(state["generation"])
        self.generator.set_state(state["generator"])


@torch.no_grad()
def load_actor_and_target(td3, vector: torch.Tensor) -> None:
    """Put ``vector`` into the TD3 actor and its target copy; clear the actor's Adam moments."""
    load_flat_parameters(td3.actor, vector)
    td3.loss.target_actor_network_params.data.update_(td3.loss.actor_network_params.data)
    td3.actor_optimizer.state.clear()


def td3_improve_member(td3, buffer, vector: torch.Tensor, updates: int) -> tuple[torch.Tensor, list[float]]:
    """CEM-RL's RL step for one member: ``updates`` TD3 updates (shared critic, this member as
    actor) on batches of ``buffer``; returns the trained flat parameters and the critic losses."""
    load_actor_and_target(td3, vector)
    critic_losses = [td3.update(buffer.sample())["critic_loss"] for _ in range(int(updates))]
    return flat_parameters(td3.actor).to(vector.device), critic_losses  # back to where the population lives (CPU)
