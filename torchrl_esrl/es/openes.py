"""OpenAI-ES over a flat parameter vector (paper, Section 2 "Evolutionary Strategies";
Salimans et al. 2017, Algorithm 2 with the paper's hyper-parameters).

``ask`` samples the population around the mean with antithetic noise pairs
(``mean + sigma * eps``, ``mean - sigma * eps``); ``tell(population, returns)`` (the ask/tell
interface of :mod:`torchrl_esrl.es.strategy`) turns the returns into centred ranks, estimates the gradient of the expected return and lets Adam step the mean.
The paper's update line ``mu <- 1/n sum F_i N_i`` drops the mean, the learning rate and
sigma; we implement the update of Salimans et al. that it cites (docs/deviations.md).
"""
from __future__ import annotations

import torch

from torchrl_esrl.es.strategy import checked_returns, strategy_holdings
from torchrl_esrl.modules.networks import flat_parameters
from torchrl_esrl.modules.population import Mirrored
from torchrl_esrl.run.capacity import Holding


def centered_ranks(values: torch.Tensor) -> torch.Tensor:
    """Fitness shaping of Salimans et al.: ranks mapped linearly to [-0.5, 0.5] (ties by order)."""
    values = values.reshape(-1)
    n = values.numel()
    if n == 1:
        return torch.zeros(1, dtype=torch.float32)
    ranks = torch.empty(n, dtype=torch.float32)
    ranks[values.argsort(stable=True)] = torch.arange(n, dtype=torch.float32)
    return ranks / (n - 1) - 0.5


class OpenES:
    """Isotropic Gaussian search distribution N(mean, sigma^2 I) whose mean follows Adam.

    Args:
        mean: initial mean (e.g. ``flat_parameters(actor)``).
        population_size: offspring per generation (even when ``antithetic``).
        sigma: standard deviation of the perturbations.
        lr: Adam learning rate on the mean.
        antithetic: mirrored sampling (pairs ``+eps``/``-eps``).
        weight_decay: L2 coefficient added to the gradient (Salimans et al. used 0.005).
        fitness_shaping: ``"centered_ranks"`` or ``"none"`` (raw returns, standardised).
        generator: torch RNG for the noise (seeded for reproducibility).
    """

    HELD_COPIES = 3  # parameter-sized vectors held (and checkpointed): the mean and Adam's two moments

    def __init__(
        self,
        mean: torch.Tensor,
        population_size: int = 120,
        sigma: float = 0.005,
        lr: float = 1e-3,
        antithetic: bool = True,
        weight_decay: float = 0.0,
        fitness_shaping: str = "centered_ranks",
        generator: torch.Generator | None = None,
    ):
        if population_size < 1 or (antithetic and population_size % 2):
            raise ValueError(f"es.population_size must be a positive{' even' if antithetic else ''} integer, got {population_size}")
        if sigma <= 0 or lr <= 0:
            raise ValueError(f"es.sigma and es.lr must be > 0, got sigma={sigma}, lr={lr}")
        if fitness_shaping not in ("centered_ranks", "none"):
            raise ValueError(f"es.fitness_shaping must be 'centered_ranks' or 'none', got {fitness_shaping!r}")
        self.mean = torch.nn.Parameter(mean.detach().clone().float().reshape(-1))
        self.population_size = int(population_size)
        self.sigma = float(sigma)
        self.antithetic = bool(antithetic)
        self.weight_decay = float(weight_decay)
        self.fitness_shaping = fitness_shaping
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.optimizer = torch.optim.Adam([self.mean], lr=lr)
        self.generation = 0
        self._noise: torch.Tensor | None = None
        self._center: torch.Tensor | None = None
        self._population: torch.Tensor | None = None  # the last ask's, until told

    @property
    def num_parameters(self) -> int:
        return self.mean.numel()

    def ask(self) -> torch.Tensor:
        """Sample the population ``[population_size, D]``; remembers the noise for :meth:`tell`."""
        half = self.population_size // 2 if self.antithetic else self.population_size
        eps = torch.randn(half, self.num_parameters, generator=self.generator)
        self._noise = torch.cat([eps, -eps]) if self.antithetic else eps
        self._center = self.mean.detach().clone()
        self._population = self._center + self.sigma * self._noise
        return self._population

    def _asked(self, population: torch.Tensor) -> bool:
        """Whether ``population`` is the last :meth:`ask`'s, not yet told."""
        asked = self._population
        return asked is not None and (population is asked or (population.shape == asked.shape and torch.equal(population, asked)))

    def mirrored(self, population: torch.Tensor) -> Mirrored | None:
        """``population``, the last :meth:`ask`'s, as mirrored pairs ``mean +- sigma * eps`` (the
        same float32 rows: ``sigma * -eps`` is ``-(sigma * eps)`` exactly); None when not
        antithetic or for any other population. Backends use it to read each pair's noise once
        (:class:`~torchrl_esrl.modules.population.Mirrored`)."""
        if not self.antithetic or not self._asked(population):
            return None
        return Mirrored(self._center, self.sigma * self._noise[: self.population_size // 2])

    def gradient(self, returns: torch.Tensor) -> torch.Tensor:
        """Search-gradient estimate of the expected return w.r.t. the mean (ascent direction)."""
        if self._noise is None:
            raise RuntimeError("OpenES.tell called before ask")
        returns = checked_returns(returns, self._population, self.generation, torch.float32)
        if self.fitness_shaping == "centered_ranks":
            weights = centered_ranks(returns)
        else:
            weights = (returns - returns.mean()) / (returns.std() + 1e-8)
        return weights @ self._noise / (self.population_size * self.sigma)

    def tell(self, population: torch.Tensor, returns: torch.Tensor) -> torch.Tensor:
        """One Adam step of the mean along the gradient estimated from the returns of
        ``population``, which must be the last :meth:`ask`'s (the estimate uses its noise);
        returns that gradient."""
        if self._noise is not None and not self._asked(population):
            raise ValueError("OpenES.tell: population is not the one the last ask returned (the gradient estimate uses its noise)")
        grad = self.gradient(returns)
        self.optimizer.zero_grad(set_to_none=False)
        # Adam minimises: feed it the negative ascent direction (plus L2 decay on the mean).
        self.mean.grad = -grad + self.weight_decay * self.mean.detach()
        self.optimizer.step()
        self._noise = self._population = None
        self.generation += 1
        return grad

    @torch.no_grad()
    def set_mean(self, vector: torch.Tensor, reset_optimizer: bool = False, mix: float = 1.0) -> None:
        """Move the mean in place to ``(1 - mix) * mean + mix * vector`` (the overwrite rule:
        ``mix=1`` replaces it, Algorithm 1; ``mix<1`` is Section 5's soft overwrite).

        With ``reset_optimizer`` Adam's moments and step count are cleared: they describe the
        path of the old mean, not the region the new one starts in.
        """
        self.mean.lerp_(vector.reshape(-1).to(device=self.mean.device, dtype=self.mean.dtype), float(mix))  # a TD3 actor's on another device
        if reset_optimizer:
            self.optimizer.state.clear()

    def state_dict(self) -> dict:
        return {
            "mean": self.mean.detach().clone(),
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "generation": self.generation,
            "sigma": self.sigma,
        }

    def load_state_dict(self, state: dict) -> None:
        self.set_mean(state["mean"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
        self.generation = int(state["generation"])
        self.sigma = float(state["sigma"])


def make_es(cfg, actor) -> OpenES:
    """OpenAI-ES of the ``es`` section whose mean starts at the (randomly initialised, near 0)
    actor's parameters, on its own noise stream (``seed + 1``)."""
    c = cfg.es
    return OpenES(
        flat_parameters(actor).cpu(),  # the ES mean lives on CPU, where populations are evaluated
        population_size=c.population_size,
        sigma=c.sigma,
        lr=c.lr,
        antithetic=c.antithetic,
        weight_decay=c.weight_decay,
        fitness_shaping=c.fitness_shaping,
        generator=torch.Generator().manual_seed(int(cfg.seed) + 1),
    )


def es_holdings(cfg, sizes) -> list[Holding]:
    """:func:`make_es`'s OpenAI-ES state and one generation (population, noise, episodes)."""
    return strategy_holdings(cfg, sizes, "es", OpenES.HELD_COPIES)
