"""Algorithm 1's ES step: g generations of OpenAI-ES whose offspring trajectories feed the buffers;
with a population step between ask and evaluation where a recipe needs one (ERL's injection of its
learner into the GA's population, :meth:`GeneticAlgorithm.inject <torchrl_esrl.es.ga.GeneticAlgorithm.inject>`)."""
from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from torchrl_esrl.algorithm.background_es import BackgroundES
from torchrl_esrl.errors import check_finite

# What a recipe may run between ask and evaluation: (population [members, D], es.generation) ->
# the population to evaluate, or None when it wrote into the one it was given.
PopulationStep = Callable[[torch.Tensor, int], "torch.Tensor | None"]


@dataclass
class GenerationsDone:
    """The ES phase under way: the returns of the iteration's generations played so far, and the
    generations played over the run (``work``, which numbers the run's checkpoints). A recipe hands
    it to the run as ``run.progress.phase``, so that a checkpoint taken between two generations
    holds it and :func:`es_phase` resumes after them."""

    returns: list[torch.Tensor] = field(default_factory=list)
    work: int = 0

    def position(self) -> str:
        return f"after ES generation {len(self.returns)} of the iteration"

    def take(self) -> list[torch.Tensor]:
        """The iteration's returns; the next iteration's phase starts from none."""
        returns, self.returns = self.returns, []
        return returns

    def state_dict(self) -> dict:
        return {"returns": torch.stack(self.returns) if self.returns else torch.empty(0), "work": self.work}

    def load_state_dict(self, state: dict) -> None:
        returns = torch.as_tensor(state["returns"])
        self.returns, self.work = [row.clone() for row in returns] if returns.numel() else [], int(state["work"])


def es_phase(
    es,
    es_collector,
    buffer,
    threshold,
    generations: int,
    shared_buffer: bool = False,
    on_generation: Callable[[int], None] | None = None,
    population_step: PopulationStep | None = None,
    at: GenerationsDone | None = None,
) -> list[torch.Tensor]:
    """Run ``generations`` generations of ``es`` (any :class:`~torchrl_esrl.es.strategy.EvolutionStrategy`:
    ask, the population step, evaluate one episode each, route, tell).

    Each offspring's trajectory goes to ``good`` when its return reaches the threshold, else to
    ``bad`` (offspring by offspring, as Algorithm 1). ``shared_buffer`` is the ERL-style ablation:
    every transition to one buffer (``noisy``), no routing. ``on_generation`` sees the index of
    each finished generation (progress display). ``population_step(population, es.generation)``,
    when given, gets a copy of each asked population before its evaluation and writes into it, or
    returns the population to evaluate instead; ``es`` is told that one (OpenAI-ES refuses a changed
    population: its update reads the noise it asked with). ``at``: the phase as far as a checkpoint
    had it (default: at its start), advanced generation by generation before ``on_generation``.
    Returns each generation's returns.
    """
    at = GenerationsDone() if at is None else at
    for index in range(len(at.returns), generations):
        population = es.ask()
        if population_step is not None:
            population = population.clone()  # the step's to change: the strategy keeps what it asked
            stepped = population_step(population, es.generation)
            population = population if stepped is None else stepped
        generation = es_collector.evaluate(population, mirrored=es.mirrored(population))
        good = threshold.route(generation.returns)
        if shared_buffer:
            buffer.extend(generation.transitions, "noisy")
        else:
            buffer.extend(generation.transitions[generation.member_mask(good)], "good")
            buffer.extend(generation.transitions[generation.member_mask(~good)], "bad")
        es.tell(population, generation.returns)  # raises on a non-finite return
        check_finite("ES mean", es.mean)
        at.returns.append(generation.returns)
        at.work += 1
        if on_generation is not None:
            on_generation(index)
    return at.take()


@dataclass
class GenerationReturns:
    """The offspring returns of one iteration's ES generations."""

    returns: list[torch.Tensor]

    def metrics(self) -> dict[str, float]:
        every = torch.cat(self.returns) if self.returns else torch.zeros(1)
        return {"es_generation_mean_return": every.mean().item(), "es_generation_max_return": every.max().item()}


class ESPhase:
    """Algorithm 1's ES step with the same two calls whether it runs inline or in the background.

    ``start()`` begins an iteration's ``generations``: with ``background`` (``es.schedule=async``) in a
    thread, alongside the TD3 phase; inline, nothing yet. ``finish()`` returns their
    :class:`GenerationReturns`: inline, it runs them there; in the background, it waits for them.
    Both halves must use ``self.buffer`` and ``self.threshold``, which are lock-guarded in the
    background mode (:mod:`~torchrl_esrl.algorithm.background_es`). ``population_step`` is
    :func:`es_phase`'s; in the background it runs in the ES thread while the TD3 phase trains, so it
    must read what it writes from a copy taken before ``start()`` (a learner's parameters as they
    stood then), never from the learner in training.
    """

    def __init__(self, es, es_collector, buffer, threshold, generations: int, shared_buffer: bool, background: bool,
                 on_generation: Callable[[int], None] | None = None, population_step: PopulationStep | None = None):
        self.background = None
        if background:
            buffer, threshold = BackgroundES.guard(buffer, threshold)
        self.progress = GenerationsDone()  # the run's ``progress.phase``: checkpoints between generations resume after them
        run = functools.partial(es_phase, es, es_collector, buffer, threshold, int(generations), bool(shared_buffer), on_generation, population_step, self.progress)
        if background:
            self.background = BackgroundES(run)
        self.es, self.es_collector, self.buffer, self.threshold, self.run = es, es_collector, buffer, threshold, run

    @property
    def inline(self) -> bool:
        """True when ES runs between the TD3 phases, so a mid-phase checkpoint sees a settled ES state."""
        return self.background is None

    def start(self) -> None:
        if self.background is not None:
            self.background.start()

    def finish(self) -> GenerationReturns:
        if self.background is not None:
            return GenerationReturns(self.background.join())
        return GenerationReturns(self.run())

    def close(self) -> None:
        if self.background is not None:
            self.background.close()


def make_es_phase(cfg, es, es_collector, buffer, threshold, on_generation: Callable[[int], None] | None = None) -> ESPhase:
    """Algorithm 1's ES step of a config: ``es.generations_per_iteration`` generations, routed to
    one buffer with ``buffer.mode=shared``; ``es.schedule=async`` runs it in a thread alongside
    the TD3 phase."""
    return ESPhase(es, es_collector, buffer, threshold, cfg.es.generations_per_iteration, shared_buffer=cfg.buffer.mode == "shared", background=cfg.es.schedule == "async", on_generation=on_generation)
