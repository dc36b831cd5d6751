"""CEM-RL (Pourchot and Sigaud, "CEM-RL: Combining evolutionary and gradient-based methods for
policy search", ICLR 2019), the baseline of ``recipes/cem_rl.py``, following the authors' code
(``ES.py`` class ``sepCEM``, ``es_grad.py``).

:class:`DiagonalCEM` is the cross-entropy method over the actor's flat parameters with a
diagonal covariance (``sepCEM``): sample ``z_i = mu + sqrt(var) * eps_i`` (antithetic pairs
``+eps, -eps`` for an even population); the top ``K`` by return are the parents, weighted
``lambda_i ∝ log((K + 1) / i)`` for rank i; the damping decays first, then

    mu_new  = sum_i lambda_i z_i
    var_new = 1/K * sum_i lambda_i (z_i - mu_old)^2 + eps,     eps <- tau eps + (1 - tau) eps_end

``sigma_init`` is the initial *variance* of every coordinate, as in the reference code.

:func:`cem_rl_gradient_steps` is the RL half of one generation: for each of the first
``rl_members`` members, load it into the TD3 actor (and its target) with a fresh Adam, run
``F // rl_members`` critic steps, then ``F`` actor steps, F = frames of the previous generation,
on ``td3.num_threads`` torch threads as TD3's own phase. Where the steps stand is a
:class:`GradientStepsPosition`: a run stopped between two steps resumes from it.

:class:`CEMConfig` is the ``cem`` config section of the recipes that build a :class:`DiagonalCEM`
(``recipe_main(..., sections={"cem": CEMConfig})``), :func:`make_cem` builds it from there.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from torchrl_esrl.errors import ConfigError
from torchrl_esrl.run.schema import number, positive

import torch

from torchrl_esrl.es.strategy import checked_returns, strategy_holdings
from torchrl_esrl.modules.networks import flat_parameters, load_flat_parameters
from torchrl_esrl.modules.population import Mirrored
from torchrl_esrl.run.capacity import Holding
from torchrl_esrl.threads import torch_threads
from torchrl_esrl.torchrl_private import foreach_lerp_


@dataclass
class CEMConfig:
    """The ``cem`` config section: sepCEM's hyper-parameters (the authors' ``ES.py`` and
    ``es_grad.py`` defaults, where the CEM-RL paper's table is silent; docs/deviations.md, 25) and
    CEM-RL's gradient-step schedule, which the CEM alone (``recipes/cem.py``) does not read."""

    population_size: int = number(10, low=2, integer=True)  # CEM-RL: 10 actors
    rl_fraction: float = number(0.5, low=0, high=1)  # CEM-RL's n_grad = 5 of 10: per member F/5 critic steps, then F actor steps
    elite_fraction: float = number(0.5, low=0, high=1, low_open=True)  # parents = pop/2 update mean and variance
    sigma_init: float = positive(1.0e-3)  # initial VARIANCE of every coordinate (reference sigma_init)
    damping_init: float = number(1.0e-3, low=0)
    damping_end: float = number(1.0e-5, low=0)
    damping_tau: float = number(0.95, low=0, high=1)
    antithetic: bool = True  # mirrored pairs +eps, -eps (the reference asserts an even population)
    start_frames: int = number(10000, low=0, integer=True)  # CEM-RL's start_steps: no gradient steps before this many frames

    @staticmethod
    def check(cem, key: str) -> None:
        """The checks across the section's keys (run by :func:`torchrl_esrl.run.config.validate_config`)."""
        if cem.antithetic and cem.population_size % 2:
            raise ConfigError(f"{key}.population_size: {cem.population_size} is invalid with {key}.antithetic=true (allowed: an even integer >= 2)")


def elite_weights(num_elites: int) -> torch.Tensor:
    """CEM-RL's rank weights ``log((K + 1) / i)``, i = 1..K, normalised to sum to 1."""
    ranks = torch.arange(1, num_elites + 1, dtype=torch.float64)
    weights = torch.log((num_elites + 1) / ranks)
    return (weights / weights.sum()).float()


class DiagonalCEM:
    """Cross-entropy method with a diagonal Gaussian (CEM-RL's ``sepCEM``), with the ask/tell
    interface of :mod:`torchrl_esrl.es.strategy`.

    Args:
        mean: initial mean (``flat_parameters(actor)``).
        population_size: samples per generation.
        sigma_init: initial variance of every coordinate (reference ``sigma_init``: 1e-3).
        elite_fraction: share of the population that updates the distribution (CEM-RL: 0.5).
        damping_init, damping_end, damping_tau: the variance floor eps added each update and its
            exponential decay, applied before the update (reference: 1e-3, 1e-5, 0.95).
        antithetic: mirrored samples ``+eps, -eps`` (the reference uses them for even populations).
        generator: torch RNG of the samples.
    """

    HELD_COPIES = 2  # parameter-sized vectors held (and checkpointed): the mean and the diagonal variance

    def __init__(
        self,
        mean: torch.Tensor,
        population_size: int = 10,
        sigma_init: float = 1e-3,
        elite_fraction: float = 0.5,
        damping_init: float = 1e-3,
        damping_end: float = 1e-5,
        damping_tau: float = 0.95,
        antithetic: bool = True,
        generator: torch.Generator | None = None,
    ):
        if population_size < 2:
            raise ValueError(f"cem.population_size must be >= 2, got {population_size}")
        self.mean = mean.detach().clone().float().reshape(-1)
        self.var = torch.full_like(self.mean, float(sigma_init))  # a variance, as the reference reads it
        self.population_size = int(population_size)
        self.num_elites = max(1, int(round(population_size * elite_fraction)))
        self.weights = elite_weights(self.num_elites)
        self.damping = float(damping_init)
        self.damping_end = float(damping_end)
        self.damping_tau = float(damping_tau)
        self.antithetic = bool(antithetic) and self.population_size % 2 == 0
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.generation = 0

    def ask(self) -> torch.Tensor:
        """Sample ``[population_size, D]`` actors from N(mean, diag(var))."""
        if self.antithetic:
            half = torch.randn(self.population_size // 2, self.mean.numel(), generator=self.generator)
            eps = torch.cat([half, -half])
        else:
            eps = torch.randn(self.population_size, self.mean.numel(), generator=self.generator)
        return self.mean + self.var.sqrt() * eps

    def mirrored(self, population: torch.Tensor) -> Mirrored | None:
        """None: CEM-RL's population is evaluated row by row (its RL half rewrites members
        before they play)."""
        return None

    def tell(self, population: torch.Tensor, returns: torch.Tensor) -> torch.Tensor:
        """Update mean and variance from the evaluated ``population`` (as evaluated, i.e. after
        the TD3 steps of its RL half); returns the elite indices, best first."""
        returns = checked_returns(returns, population, self.generation, torch.float64)
        elites = returns.argsort(descending=True, stable=True)[: self.num_elites]
        z = population[elites].float()
        old_mean = self.mean
        self.damping = self.damping_tau * self.damping + (1 - self.damping_tau) * self.damping_end  # decayed before use
        self.mean = self.weights @ z
        self.var = self.weights @ (z - old_mean) ** 2 / self.num_elites + self.damping
        self.generation += 1
        return elites

    @torch.no_grad()
    def set_mean(self, vector: torch.Tensor, reset_optimizer: bool = False, mix: float = 1.0) -> None:
        """Move the mean to ``(1 - mix) * mean + mix * vector`` (the overwrite rule, as
        :meth:`OpenES.set_mean <torchrl_esrl.es.openes.OpenES.set_mean>`); the variance stays.
        ``reset_optimizer`` changes nothing: CEM keeps no optimiser state."""
        self.mean = self.mean.lerp(vector.reshape(-1).to(self.mean.dtype), float(mix))

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


def _lerp_pairs(target, source) -> tuple[list, list]:
    """The tensors of ``target`` and ``source`` (the loss's parameter TensorDicts) paired by key, for
    one ``torch._foreach_lerp_`` a step: what ``target.data.lerp_(source.data, tau)`` computes, without
    flattening both TensorDicts again every step. Valid until a parameter's ``.data`` is rebound, as
    :func:`~torchrl_esrl.modules.networks.load_flat_parameters` does."""
    keys = list(source.keys(True, True))
    return [target.get(key).data for key in keys], [source.get(key).data for key in keys]


def _gradient_step(td3, name: str, loss_fn, optimizer, targets: list, sources: list, batch, tau: float, member: int) -> float:
    """One Adam step on ``loss_fn(batch)`` as TD3 takes its own (:meth:`TD3.gradient_step
    <torchrl_esrl.objectives.td3.TD3.gradient_step>`: its precision and its ``backward``, where a
    subclass adds a loss term or clips), then the soft update of that network's target only."""
    value = td3.gradient_step(loss_fn, batch, optimizer, f"CEM-RL {name} loss while training member {member}")
    foreach_lerp_(targets, sources, tau)
    return value


@dataclass
class GradientStepsPosition:
    """Where the gradient steps of one generation stand (:func:`cem_rl_gradient_steps` resumes from
    it): the member in training and its critic and actor steps taken, and the generation's step
    counts and critic losses so far."""

    member: int = 0
    member_critic_steps: int = 0
    member_actor_steps: int = 0
    critic_steps: int = 0
    actor_steps: int = 0
    critic_losses: list[float] = field(default_factory=list)

    @property
    def steps(self) -> int:
        return self.critic_steps + self.actor_steps

    COUNTS = ("member", "member_critic_steps", "member_actor_steps", "critic_steps", "actor_steps")

    def state_dict(self) -> dict:
        return {**{key: getattr(self, key) for key in self.COUNTS}, "critic_losses": torch.tensor(self.critic_losses, dtype=torch.float64)}

    def load_state_dict(self, state: dict) -> None:
        for key in self.COUNTS:
            setattr(self, key, int(state[key]))
        self.critic_losses = torch.as_tensor(state["critic_losses"]).tolist()  # float64: the floats as they were


def cem_rl_gradient_steps(td3, buffer, population: torch.Tensor, rl_members: int, frames: int, tau: float,
                          at: GradientStepsPosition | None = None, on_step: Callable[[], None] | None = None) -> dict:
    """The RL half of one CEM-RL generation (reference ``es_grad.py``), in place on ``population``.

    For each of the first ``rl_members`` members: load it into the actor and the actor target,
    clear the actor's Adam (a fresh optimiser); ``frames // rl_members`` critic steps (TD3's twin
    critic loss with target smoothing, critic target soft-updated), then ``frames`` actor steps
    (``-Q1(s, pi(s))``, actor target soft-updated); write the actor back into the population.
    The critic and its Adam are shared across members and generations. ``frames`` is F, the
    number of frames the previous generation played. The steps run on ``td3.num_threads`` torch
    threads (default: this job's share of the cores, torchrl_esrl/threads.py), as
    :func:`~torchrl_esrl.algorithm.td3_phase.td3_phase` runs TD3's. Returns the step counts and
    critic losses.

    ``at``: where the steps stand, advanced after every step (default: from the start);
    ``on_step()`` is called after each (a stop point). From a position mid-member, the TD3
    learner is the one checkpointed there: its actor takes its member's row as storage again, as
    it had (on another device than the population, it keeps the values restored), and its target
    and Adam are kept.
    """
    at = GradientStepsPosition() if at is None else at
    loss = td3.loss
    critic_per_member, actor_per_member = int(frames) // int(rl_members), int(frames)
    with torch_threads(td3.num_threads):
        while at.member < int(rl_members):
            member = at.member
            if at.member_critic_steps == 0 and at.member_actor_steps == 0:
                load_actor_and_target(td3, population[member])  # rebinds the actor's parameters: pair them after it
            elif population.device == next(td3.actor.parameters()).device:
                load_flat_parameters(td3.actor, population[member])  # the row holds the actor's values: the same storage as before the stop
            # (an actor on another device, device=cuda, held a copy of the row: it is as the checkpoint restored it)
            critic = ("critic", loss.value_loss, td3.critic_optimizer, *_lerp_pairs(loss.target_qvalue_network_params, loss.qvalue_network_params))
            actor = ("actor", loss.actor_loss, td3.actor_optimizer, *_lerp_pairs(loss.target_actor_network_params, loss.actor_network_params))
            while at.member_critic_steps < critic_per_member:
                at.critic_losses.append(_gradient_step(td3, *critic, buffer.sample(), tau, member))
                at.member_critic_steps += 1
                at.critic_steps += 1
                if on_step is not None:
                    on_step()
            while at.member_actor_steps < actor_per_member:
                _gradient_step(td3, *actor, buffer.sample(), tau, member)
                at.member_actor_steps += 1
                at.actor_steps += 1
                if on_step is not None:
                    on_step()
            population[member] = flat_parameters(td3.actor)
            at.member, at.member_critic_steps, at.member_actor_steps = member + 1, 0, 0
    td3.updates += at.critic_steps
    return {"critic_steps": at.critic_steps, "actor_steps": at.actor_steps, "critic_losses": at.critic_losses}


def make_cem(cfg, actor) -> DiagonalCEM:
    """The diagonal CEM of the ``cem`` section centred on the actor's parameters, on its own noise
    stream (``seed + 1``)."""
    c = cfg.cem
    return DiagonalCEM(
        flat_parameters(actor).cpu(),
        population_size=c.population_size,
        sigma_init=c.sigma_init,
        elite_fraction=c.elite_fraction,
        damping_init=c.damping_init,
        damping_end=c.damping_end,
        damping_tau=c.damping_tau,
        antithetic=c.antithetic,
        generator=torch.Generator().manual_seed(int(cfg.seed) + 1),
    )


def cem_holdings(cfg, sizes) -> list[Holding]:
    """:func:`make_cem`'s CEM state and one generation (population, noise, episodes), for the
    run's memory estimate (:mod:`torchrl_esrl.run.capacity`)."""
    return strategy_holdings(cfg, sizes, "cem", DiagonalCEM.HELD_COPIES)
