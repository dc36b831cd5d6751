"""ERL's genetic algorithm (Khadka and Tumer, "Evolution-Guided Policy Gradient in Reinforcement
Learning", NeurIPS 2018) over actors' flat parameters, with the ask/tell interface of
:mod:`torchrl_esrl.es.strategy`. The operators and numbers are those of the authors' code
(``core/mod_neuro_evo.py``, class ``SSNE``; ``run_erl.py``, class ``Parameters``; public copies such
as ``zhan0903/erl_paper_nips18``).

One generation (:meth:`GeneticAlgorithm.tell`), from the population as evaluated and its returns
(each member's fitness the mean return of its ``evaluations`` episodes, the authors' ``num_evals``):

- **Selection.** Members ranked by return; the best ``elite_fraction`` are the elites (at least
  one). ``population_size - elites`` tournaments of ``tournament_size`` draws (with replacement,
  the best rank wins); the distinct winners are the offspring, in member order, one of them repeated
  at random when their count is odd. The others, neither elite nor winner, are the unselected, shuffled.
- **Elitism.** Each elite, best first, is copied over the next unselected member (over an offspring
  once none is left): those copies are the new elites, left unchanged this generation.
- **Crossover.** The remaining unselected in pairs (one repeated at random when their count is
  odd): the first becomes a copy of a random new elite, the second of a random offspring, and the
  two cross. Pairs of offspring cross with probability ``crossover_prob``. Two members cross layer
  by layer: a weight matrix ``[out, in]`` gets ``U{0, ..., 2 out - 1}`` row copies, each a random row
  (a neuron's incoming weights) copied from one member into the other, either way with probability
  1/2; a bias ``[out]`` gets ``U{0, ..., out - 1}`` such element copies.
- **Mutation.** Every member but the new elites, with probability ``mutation_prob``: each weight
  matrix, with probability ``min(1, 2u)`` (u ~ U(0, 1) per layer), gets ``U{0, ..., ceil(mutation_fraction
  n) - 1}`` mutations of random entries (n entries; an entry drawn twice mutates twice, in draw
  order): with probability ``super_mutation_prob`` ``w += N(0, (super_mutation_strength w)^2)``,
  with probability ``reset_prob`` ``w = N(0, 1)``, else ``w += N(0, (mutation_strength w)^2)``,
  each result clamped to ``[-weight_limit, weight_limit]``. Biases are not mutated.

The authors' numbers, the defaults here: population 10; elite fraction 0.1 (HalfCheetah, Swimmer;
0.2 on Walker2d and Reacher, 0.3 on Hopper and Ant); tournaments of 3; crossover probability 0.0 between
offspring; mutation probability 0.9; mutated fraction 0.1, strength 0.1; super mutation 0.05 at
strength 10; reset 0.05; weight limit 1e6; one episode per member (3 on Walker2d, 5 on Hopper). ERL
copies its learner over the member that scored lowest (:meth:`GeneticAlgorithm.weakest`,
:meth:`GeneticAlgorithm.inject`) every 10 generations (every generation on Hopper and Ant);
docs/deviations.md, 42-43.

:class:`GAConfig` is the ``ga`` config section of the recipes that build a GA
(``recipe_main(..., sections={"ga": GAConfig})``), :func:`make_ga` builds it from there and
:func:`ga_holdings` says what it holds.
"""
from __future__ import annotations

import copy
import math
from collections.abc import Sequence

from dataclasses import dataclass

import torch
from torch import nn

from torchrl_esrl.errors import ConfigError
from torchrl_esrl.es.strategy import checked_returns
from torchrl_esrl.modules.networks import actor_parameters, cpu_actor, flat_parameters
from torchrl_esrl.modules.population import Mirrored
from torchrl_esrl.run.capacity import Holding, bytes_per_transition, network_holding, population_holdings
from torchrl_esrl.run.schema import count, number, positive


@dataclass
class GAConfig:
    """The ``ga`` config section: ERL's genetic algorithm, the authors' values (``run_erl.py``'s
    ``Parameters``, ``mod_neuro_evo.py``'s ``SSNE``; docs/deviations.md, 43) on HalfCheetah and Swimmer;
    ``conf/erl_env/`` sets those of Walker2d, Hopper and Ant."""

    population_size: int = number(10, low=2, integer=True)
    elite_fraction: float = number(0.1, low=0, high=1)  # at least one elite, at most half the members (check)
    tournament_size: int = count(3)
    crossover_prob: float = number(0.0, low=0, high=1)  # between selected offspring (the unselected always cross)
    mutation_prob: float = number(0.9, low=0, high=1)  # per member, the new elites spared
    mutation_fraction: float = number(0.1, low=0, high=1, low_open=True)  # entries of a weight matrix mutated at most
    mutation_strength: float = positive(0.1)
    super_mutation_strength: float = positive(10.0)
    super_mutation_prob: float = number(0.05, low=0, high=1)
    reset_prob: float = number(0.05, low=0, high=1)
    weight_limit: float = positive(1.0e6)
    evaluations: int = count(1)  # episodes per member, fitness their mean (num_evals)

    @staticmethod
    def check(ga, key: str) -> None:
        """The checks across the section's keys (run by :func:`torchrl_esrl.run.config.validate_config`)."""
        if 2 * max(1, int(ga.elite_fraction * ga.population_size)) > ga.population_size:
            raise ConfigError(f"{key}.elite_fraction: {ga.elite_fraction} leaves fewer members than elites in a population of {ga.population_size} (allowed: at most half the members elites, at least one)")
        if ga.super_mutation_prob + ga.reset_prob > 1:
            raise ConfigError(f"{key}.reset_prob: {ga.super_mutation_prob} + {ga.reset_prob} is invalid (allowed: {key}.super_mutation_prob + {key}.reset_prob <= 1)")


def parameter_shapes(actor: nn.Module) -> list[torch.Size]:
    """The shapes of ``actor.parameters()``, in the order of its flat vector
    (:func:`~torchrl_esrl.modules.networks.flat_parameters`): the layer layout the GA's operators read."""
    return [p.shape for p in actor.parameters()]


def initial_population(actor: nn.Module, size: int, generator: torch.Generator) -> torch.Tensor:
    """``[size, D]``: ``size`` actors of ``actor``'s architecture, each initialised afresh by its
    layers' own ``reset_parameters`` (PyTorch's default initialisation, as ERL's population is built),
    under a seed drawn from ``generator``, on CPU (where the population lives) whatever device ``actor`` is on."""
    members = []
    for _ in range(int(size)):
        seed = int(torch.randint(2**62, (1,), generator=generator))
        member = copy.deepcopy(cpu_actor(actor))
        layers = [module for module in member.modules() if callable(getattr(module, "reset_parameters", None))]
        if not layers:
            raise ValueError(f"initial_population: {type(actor).__name__} has no layer with reset_parameters to initialise")
        with torch.random.fork_rng(devices=[]):
            torch.default_generator.manual_seed(seed)  # CPU's alone: torch.manual_seed would reseed CUDA's too, which fork_rng(devices=[]) leaves
            for layer in layers:
                layer.reset_parameters()
        members.append(flat_parameters(member))
    return torch.stack(members)


class GeneticAlgorithm:
    """ERL's genetic algorithm over a population ``[population_size, D]`` of flat actor parameters.

    Args:
        population: the initial population (:func:`initial_population`; :meth:`for_actor` builds both).
        shapes: the layer layout of a row (:func:`parameter_shapes`): weight matrices ``[out, in]``
            and bias vectors ``[out]``, in the order of the flat vector.
        elite_fraction, tournament_size, crossover_prob, mutation_prob, mutation_fraction,
        mutation_strength, super_mutation_strength, super_mutation_prob, reset_prob, weight_limit:
            the operators' numbers (module docstring).
        evaluations: episodes per member: ``ask`` gives each member this many consecutive rows,
            ``tell`` takes one return per row and a member's fitness is the mean of its rows'.
        generator: torch RNG of every random draw.

    ``ask`` returns a copy of the population; ``tell(population, returns)`` takes the population as
    evaluated (a population step may have written into it, every row of a member alike) and breeds
    the next one. The state a
    checkpoint holds: the population (``population_size`` parameter vectors), the last returns,
    the champion's row, the generator and the generation count.
    """

    def __init__(
        self,
        population: torch.Tensor,
        shapes: Sequence[torch.Size],
        elite_fraction: float = 0.1,
        tournament_size: int = 3,
        crossover_prob: float = 0.0,
        mutation_prob: float = 0.9,
        mutation_fraction: float = 0.1,
        mutation_strength: float = 0.1,
        super_mutation_strength: float = 10.0,
        super_mutation_prob: float = 0.05,
        reset_prob: float = 0.05,
        weight_limit: float = 1e6,
        evaluations: int = 1,
        generator: torch.Generator | None = None,
    ):
        if population.dim() != 2 or population.shape[0] < 2:
            raise ValueError(f"ga.population_size must be >= 2, got a population of shape {tuple(population.shape)}")
        size = population.shape[0]
        self.num_elites = max(1, int(elite_fraction * size))
        if not 0 <= elite_fraction or 2 * self.num_elites > size:
            raise ValueError(f"ga.elite_fraction must leave at least as many members as elites (at most 0.5), got {elite_fraction}")
        if tournament_size < 1:
            raise ValueError(f"ga.tournament_size must be >= 1, got {tournament_size}")
        for name, value in (("crossover_prob", crossover_prob), ("mutation_prob", mutation_prob), ("super_mutation_prob", super_mutation_prob), ("reset_prob", reset_prob)):
            if not 0 <= value <= 1:
                raise ValueError(f"ga.{name} must be in [0, 1], got {value}")
        if super_mutation_prob + reset_prob > 1:
            raise ValueError(f"ga.super_mutation_prob + ga.reset_prob must be <= 1, got {super_mutation_prob} + {reset_prob}")
        if int(evaluations) < 1:
            raise ValueError(f"ga.evaluations must be >= 1, got {evaluations}")
        if not 0 < mutation_fraction <= 1 or weight_limit <= 0:
            raise ValueError(f"ga.mutation_fraction must be in (0, 1] and ga.weight_limit > 0, got {mutation_fraction}, {weight_limit}")
        self.layers, offset = [], 0
        for shape in shapes:
            shape = torch.Size(shape)
            if len(shape) not in (1, 2):
                raise ValueError(f"GeneticAlgorithm: a parameter of shape {tuple(shape)}; ERL's operators read weight matrices [out, in] and bias vectors [out]")
            self.layers.append((offset, shape))
            offset += shape.numel()
        if offset != population.shape[1]:
            raise ValueError(f"GeneticAlgorithm: the layer shapes hold {offset} parameters, a population row {population.shape[1]}")
        self.population = population.detach().clone().float()
        self.tournament_size = int(tournament_size)
        self.crossover_prob, self.mutation_prob = float(crossover_prob), float(mutation_prob)
        self.mutation_fraction, self.mutation_strength = float(mutation_fraction), float(mutation_strength)
        self.super_mutation_strength, self.super_mutation_prob = float(super_mutation_strength), float(super_mutation_prob)
        self.reset_prob, self.weight_limit = float(reset_prob), float(weight_limit)
        self.evaluations = int(evaluations)
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.generation = 0
        self.returns: torch.Tensor | None = None  # the last told generation's fitness, by member
        self.champion_row = 0  # where the best member of the last told generation was copied

    @classmethod
    def for_actor(cls, actor: nn.Module, population_size: int, generator: torch.Generator | None = None, **operators) -> GeneticAlgorithm:
        """A GA over ``actor``'s parameters: ``population_size`` actors initialised afresh
        (:func:`initial_population`, from ``generator``) and ``actor``'s layer layout."""
        generator = generator if generator is not None else torch.Generator().manual_seed(0)
        return cls(initial_population(actor, population_size, generator), parameter_shapes(actor), generator=generator, **operators)

    @property
    def population_size(self) -> int:
        return self.population.shape[0]

    @property
    def champion(self) -> torch.Tensor:
        """The best member of the last told generation, as evaluated (a copy of its elite copy, which
        no operator changed); row 0 before the first tell."""
        return self.population[self.champion_row].clone()

    @property
    def mean(self) -> torch.Tensor:
        """The returned policy under the ask/tell interface's name for it
        (:mod:`~torchrl_esrl.es.strategy`): the :attr:`champion`. A GA has no search distribution."""
        return self.champion

    def ask(self) -> torch.Tensor:
        """The population to evaluate, ``[population_size * evaluations, D]``: each member's
        ``evaluations`` rows in a row (a copy: the GA's own stays as it is until told)."""
        return self.population.repeat_interleave(self.evaluations, dim=0)

    def members(self, population: torch.Tensor) -> torch.Tensor:
        """``population`` (as asked) by member, ``[population_size, evaluations, D]``: a view, to write a member's rows at once."""
        return population.view(self.population_size, self.evaluations, -1)

    def mirrored(self, population: torch.Tensor) -> Mirrored | None:
        """None: the GA's members are evaluated row by row."""
        return None

    def weakest(self) -> int:
        """The member that scored lowest in the last told generation (the first on ties), where ERL
        copies its learner; after that tell its place holds one of the new generation's members."""
        if self.returns is None:
            raise RuntimeError("GeneticAlgorithm.weakest: no generation was told yet")
        return int(self.returns.argmin())

    @torch.no_grad()
    def inject(self, population: torch.Tensor, vector: torch.Tensor) -> int:
        """Write ``vector`` (a learner's flat parameters) over the :meth:`weakest` member of
        ``population`` (an asked population, before its evaluation: all of that member's rows);
        returns that member."""
        member = self.weakest()
        self.members(population)[member] = vector.reshape(-1).to(population.dtype)
        return member

    def is_elite(self, member: int) -> bool:
        """Whether ``member`` of the last told generation was one of its elites (fewer better than it)."""
        if self.returns is None:
            raise RuntimeError("GeneticAlgorithm.is_elite: no generation was told yet")
        return int((self.returns > self.returns[member]).sum()) < self.num_elites

    def _randint(self, high: int) -> int:
        return int(torch.randint(high, (1,), generator=self.generator))

    def _rand(self) -> float:
        return float(torch.rand(1, generator=self.generator))

    @torch.no_grad()
    def tell(self, population: torch.Tensor, returns: torch.Tensor) -> torch.Tensor:
        """Breed the next population from ``population`` as evaluated (as asked: each member's
        ``evaluations`` rows in a row) and the returns of its rows (selection, elitism, crossover,
        mutation on the members' fitness, the mean of their rows'; module docstring); returns the
        new elites' members, best first."""
        expected = (self.population_size * self.evaluations, self.population.shape[1])
        if tuple(population.shape) != expected:
            raise ValueError(f"GeneticAlgorithm.tell: a population of shape {tuple(population.shape)}, expected {expected}")
        returns = checked_returns(returns, population, self.generation, torch.float64).view(self.population_size, self.evaluations).mean(1)
        by_member = self.members(population.detach())
        if not torch.equal(by_member, by_member[:, :1].expand_as(by_member)):
            raise ValueError("GeneticAlgorithm.tell: a member's rows differ; a population step must write all of a member's rows alike (members())")
        members = by_member[:, 0].clone().float()
        size = self.population_size
        rank = returns.argsort(descending=True, stable=True).tolist()
        elites = rank[: self.num_elites]
        draws = torch.randint(size, (size - self.num_elites, self.tournament_size), generator=self.generator)
        offspring = sorted({rank[winner] for winner in draws.min(dim=1).values.tolist()})
        if len(offspring) % 2:
            offspring.append(offspring[self._randint(len(offspring))])
        unselected = [i for i in range(size) if i not in offspring and i not in elites]
        unselected = [unselected[k] for k in torch.randperm(len(unselected), generator=self.generator).tolist()]
        new_elites = []
        for elite in elites:
            replaced = unselected.pop(0) if unselected else offspring.pop(0)
            members[replaced] = members[elite]
            new_elites.append(replaced)
        if len(unselected) % 2:
            unselected.append(unselected[self._randint(len(unselected))])
        for first, second in zip(unselected[0::2], unselected[1::2]):
            members[first] = members[new_elites[self._randint(len(new_elites))]]
            members[second] = members[offspring[self._randint(len(offspring))]]
            self.crossover(members[first], members[second])
        for first, second in zip(offspring[0::2], offspring[1::2]):
            if self._rand() < self.crossover_prob:
                self.crossover(members[first], members[second])
        for member in range(size):
            if member not in new_elites and self._rand() < self.mutation_prob:
                self.mutate(members[member])
        self.population, self.returns, self.champion_row = members, returns, new_elites[0]
        self.generation += 1
        return torch.tensor(new_elites)

    def _layer(self, row: torch.Tensor, offset: int, shape: torch.Size) -> torch.Tensor:
        return row[offset : offset + shape.numel()].view(shape)

    @torch.no_grad()
    def crossover(self, first: torch.Tensor, second: torch.Tensor) -> None:
        """Cross two member rows in place, layer by layer (module docstring). Copies that pick a row
        already copied change nothing (both members hold it alike since its first copy), so each
        row's first copy, in draw order, is the one applied."""
        for offset, shape in self.layers:
            a, b = self._layer(first, offset, shape), self._layer(second, offset, shape)
            rows = shape[0]
            count = self._randint(2 * rows if len(shape) == 2 else rows)
            if count == 0:
                continue
            picked = torch.randint(rows, (count,), generator=self.generator)
            into_first = torch.rand(count, generator=self.generator) < 0.5
            first_copy = torch.full((rows,), count).scatter_reduce_(0, picked, torch.arange(count), "amin")
            copied = first_copy < count
            to_first = copied & into_first[first_copy.clamp(max=count - 1)]
            to_second = copied & ~to_first
            a[to_first] = b[to_first]
            b[to_second] = a[to_second]

    @torch.no_grad()
    def mutate(self, member: torch.Tensor) -> None:
        """Mutate one member row in place, weight matrix by weight matrix (module docstring)."""
        chances = 2 * torch.rand(len(self.layers), generator=self.generator)
        for (offset, shape), chance in zip(self.layers, chances.tolist()):
            if len(shape) != 2 or self._rand() >= chance:
                continue
            weights = member[offset : offset + shape.numel()]
            count = self._randint(math.ceil(self.mutation_fraction * shape.numel()))
            if count == 0:
                continue
            entries = torch.randint(shape.numel(), (count,), generator=self.generator)
            kind = torch.rand(count, generator=self.generator)
            noise = torch.randn(count, generator=self.generator)
            for chosen in _in_rounds(entries):  # an entry's second mutation after its first
                w, u, z = weights[entries[chosen]], kind[chosen], noise[chosen]
                strength = torch.where(u < self.super_mutation_prob, self.super_mutation_strength, self.mutation_strength)
                reset = (u >= self.super_mutation_prob) & (u < self.super_mutation_prob + self.reset_prob)
                weights[entries[chosen]] = torch.where(reset, z, w + strength * w * z).clamp(-self.weight_limit, self.weight_limit)

    def state_dict(self) -> dict:
        return {
            "population": self.population.clone(),
            "returns": self.returns.clone() if self.returns is not None else torch.empty(0, dtype=torch.float64),
            "champion_row": self.champion_row,
            "generator": self.generator.get_state(),
            "generation": self.generation,
        }

    def load_state_dict(self, state: dict) -> None:
        population = torch.as_tensor(state["population"])
        if population.shape != self.population.shape:
            raise ValueError(f"GeneticAlgorithm: a checkpointed population of shape {tuple(population.shape)}, this GA's is {tuple(self.population.shape)}")
        returns = torch.as_tensor(state["returns"])
        self.population = population.clone().float()
        self.returns = returns.clone() if returns.numel() else None
        self.champion_row, self.generation = int(state["champion_row"]), int(state["generation"])
        self.generator.set_state(state["generator"])


def make_ga(cfg, actor) -> GeneticAlgorithm:
    """The genetic algorithm of the ``ga`` section over ``actor``'s parameters: ``ga.population_size``
    actors initialised afresh, on its own stream (``seed + 1``)."""
    c = cfg.ga
    operators = {key: c[key] for key in ("elite_fraction", "tournament_size", "crossover_prob", "mutation_prob", "mutation_fraction", "mutation_strength",
                                        "super_mutation_strength", "super_mutation_prob", "reset_prob", "weight_limit", "evaluations")}
    return GeneticAlgorithm.for_actor(actor, int(c.population_size), torch.Generator().manual_seed(int(cfg.seed) + 1), **operators)


def ga_holdings(cfg, sizes) -> list[Holding]:
    """What :func:`make_ga` holds, for the run's memory estimate (:mod:`torchrl_esrl.run.capacity`):
    its population (checkpointed), and one generation as evaluated (the asked rows, the population
    step's copy, the episodes until they are routed)."""
    c, parameters = cfg.ga, actor_parameters(cfg, sizes)
    field = "ga.population_size"
    rows = int(c.population_size) * int(c.evaluations)
    transition = bytes_per_transition(sizes.observation_dim, sizes.action_dim)
    return [network_holding(int(c.population_size), parameters, field), *population_holdings(parameters, rows, False, sizes.episode_steps, transition, field)]


def _in_rounds(entries: torch.Tensor) -> list[torch.Tensor]:
    """Masks over ``entries`` (draws of positions, with repetition) in rounds: round k holds each
    position's (k+1)-th draw, so no position twice in a round, and applying the rounds in turn
    applies every position's draws in draw order."""
    count = entries.numel()
    order = entries.argsort(stable=True)
    ordered = entries[order]
    starts = torch.ones(count, dtype=torch.bool)
    starts[1:] = ordered[1:] != ordered[:-1]
    group_start = torch.where(starts, torch.arange(count), 0).cummax(0).values
    repeat = torch.empty(count, dtype=torch.long)
    repeat[order] = torch.arange(count) - group_start
    return [repeat == k for k in range(int(repeat.max()) + 1)]
