"""The ask/tell interface every evolution strategy of the project has (OpenAI-ES, CEM, ERL's GA).

    population = es.ask()                                      # [members, D], one row per member
    generation = es_collector.evaluate(population, mirrored=es.mirrored(population))
    es.tell(population, generation.returns)                    # the returns in the rows' order

Between ask and evaluation a recipe may change members (ERL's injection; the population step of
:func:`~torchrl_esrl.algorithm.es_phase.es_phase`): ``tell`` takes the population as evaluated, or
refuses it where its update needs the one it asked (OpenAI-ES).

``es.mean`` is the search distribution's centre (the policy a recipe returns), ``es.set_mean``
moves it (the overwrite rule of Algorithm 1), ``es.generation`` counts the tells and
``state_dict``/``load_state_dict`` checkpoint it. :func:`~torchrl_esrl.algorithm.es_phase.es_phase`
runs any strategy with this interface.
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch

from torchrl_esrl.modules.networks import NETWORK_FIELD, actor_parameters
from torchrl_esrl.modules.population import Mirrored
from torchrl_esrl.run.capacity import Holding, bytes_per_transition, network_holding, population_holdings


@runtime_checkable
class EvolutionStrategy(Protocol):
    """What :func:`~torchrl_esrl.algorithm.es_phase.es_phase` and the recipes call on an ES."""

    mean: torch.Tensor
    generation: int

    def ask(self) -> torch.Tensor:
        """The population to evaluate, ``[members, D]``."""

    def mirrored(self, population: torch.Tensor) -> Mirrored | None:
        """``population`` as mirrored pairs, when it is the asked antithetic population (the
        fast evaluation reads each pair's noise once), else None: evaluate the flat rows."""

    def tell(self, population: torch.Tensor, returns: torch.Tensor):
        """Update the search distribution from the returns of ``population``'s rows."""

    def set_mean(self, vector: torch.Tensor, reset_optimizer: bool = False, mix: float = 1.0) -> None:
        """Move the mean to ``(1 - mix) * mean + mix * vector``."""

    def state_dict(self) -> dict: ...

    def load_state_dict(self, state: dict) -> None: ...


def checked_returns(returns, population: torch.Tensor, generation: int, dtype: torch.dtype) -> torch.Tensor:
    """``returns`` as a flat ``dtype`` tensor, one per row of ``population``; raises on another
    count or on a non-finite return (a diverged rollout must not move the search distribution)."""
    returns = torch.as_tensor(returns, dtype=dtype).reshape(-1)
    if returns.numel() != population.shape[0]:
        raise ValueError(f"expected {population.shape[0]} returns, got {returns.numel()}")
    if not torch.isfinite(returns).all():
        raise FloatingPointError(f"non-finite episode return in ES generation {generation}: {returns.tolist()}")
    return returns


def strategy_holdings(cfg, sizes, section: str, copies: int) -> list[Holding]:
    """What the strategy of config section ``section`` (its ``population_size`` and ``antithetic``)
    holds, for the run's memory estimate (:mod:`torchrl_esrl.run.capacity`): ``copies``
    parameter-sized vectors of its state, and one generation (population, noise, episodes)."""
    c, parameters = cfg[section], actor_parameters(cfg, sizes)
    transition = bytes_per_transition(sizes.observation_dim, sizes.action_dim)
    field = f"{section}.population_size"
    return [network_holding(copies, parameters, NETWORK_FIELD), *population_holdings(parameters, int(c.population_size), bool(c.antithetic), sizes.episode_steps, transition, field)]
