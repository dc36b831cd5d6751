"""The implementation switch: the one reader of the ``implementation`` key, and the pieces line.

``reference`` builds stock TorchRL end to end (``TD3Loss`` with autograd, ``SoftUpdate``,
``torch.optim.Adam``, TorchRL's ``Collector`` over ``GymEnv``, the buffers' own ``extend`` and
storage reads, and an ES evaluation that runs the actor module through ``functional_call`` in
gymnasium); ``fast`` swaps in the pieces of :data:`FAST_PIECES`, each a class beside the
reference it replaces, each proven equal to it (docs/performance.md). The component factories
(``make_td3`` beside ``objectives/td3.py``, ``make_multibuffer`` beside ``data/multibuffer.py``...)
take the pieces :func:`chosen_pieces` gives them; a fast piece that cannot compute exactly what
its reference would (another layer, transform or loss) hands over to the reference, and
:func:`implementations` says which ran and why.
"""
from __future__ import annotations

from collections.abc import Collection

from omegaconf import DictConfig

IMPLEMENTATIONS = ("fast", "reference")
# Each fast piece, and the reference it replaces (docs/performance.md has the table):
FAST_PIECES = {
    "td3_loss": "ManualGradTD3Loss (hand-written gradients beneath loss.backward()) <- TorchRL TD3Loss + autograd",
    "soft_update": "ForeachSoftUpdate <- TorchRL SoftUpdate",
    "adam": "fused Adam, one kernel call <- torch.optim.Adam",
    "td3_collector": "GymTD3Collector <- TorchRL Collector over GymEnv",
    "buffer_writes": "MultiBuffer(direct_writes) <- TensorDictReplayBuffer.extend",
    "buffer_reads": "MultiBuffer(direct_reads) <- each buffer's storage get",
    "es_forward": "PopulationActor (batched, mirrored pairs) <- ModulePopulation (functional_call)",
    "es_physics": "mujoco_batch backend <- gym backend (es.backend=auto)",
}


def fast_pieces(cfg: DictConfig) -> frozenset[str]:
    """The fast pieces the config asks for: all of :data:`FAST_PIECES` with
    ``implementation=fast``, none with ``implementation=reference``."""
    return frozenset(FAST_PIECES) if cfg.implementation == "fast" else frozenset()


def chosen_pieces(cfg: DictConfig, pieces: Collection[str] | None) -> frozenset[str]:
    """The fast pieces a factory builds with: ``pieces`` where given (``benchmarks.iteration
    --ablation`` switches one back), else :func:`fast_pieces` of the config."""
    return fast_pieces(cfg) if pieces is None else frozenset(pieces)


def component(components: dict, kind: type):
    """The first of a recipe's ``components`` (name -> object, as given to ``Run.start``) that is a
    ``kind``, or None: the run plumbing finds a component by what it is, not by its name."""
    return next((value for value in components.values() if isinstance(value, kind)), None)


def implementations(cfg: DictConfig, **components) -> dict[str, str]:
    """What computes each piece of :data:`FAST_PIECES` in this run: ``fast``, ``reference``, or
    ``reference (why)`` where ``implementation=fast`` asked for the fast piece and it handed over
    (``es_physics: reference (env.wrappers: ClipReward)``). ``components`` are the recipe's, found
    by what they are, whatever the recipe calls them (a :class:`~torchrl_esrl.objectives.learner.Learner`,
    which says which of its update's pieces run, a ``TD3EnvState``, a
    :class:`MultiBuffer`, an :class:`ESCollector`; others are ignored); a piece the run does not
    have is left out."""
    from torchrl_esrl.collectors.es_collector import ESCollector
    from torchrl_esrl.collectors.mujoco_batch import MujocoBatchBackend
    from torchrl_esrl.collectors.td3_collector import GymTD3Collector, TD3EnvState, _refusal
    from torchrl_esrl.data.multibuffer import MultiBuffer
    from torchrl_esrl.modules.population import PopulationActor
    from torchrl_esrl.objectives.learner import Learner

    asked = fast_pieces(cfg)

    def piece(name: str, fast: bool, why: str | None = None) -> None:
        if fast:
            out[name] = "fast"
        elif name in asked:
            out[name] = f"reference ({why})" if why else "reference"
        else:
            out[name] = "reference"

    out: dict[str, str] = {}
    learner = component(components, Learner)
    if learner is not None:
        for name, (fast, why) in learner.pieces().items():
            piece(name, fast, why)
    td3_env = component(components, TD3EnvState)
    if td3_env is not None:
        collector = td3_env.collector
        fast = isinstance(collector, GymTD3Collector)
        piece("td3_collector", fast, None if fast or learner is None else _refusal(collector.env, learner.exploration_policy, cfg.device))
    buffer = component(components, MultiBuffer)
    if buffer is not None:
        piece("buffer_writes", buffer.direct_writes)
        piece("buffer_reads", buffer.storage.direct_reads)
    es_collector = component(components, ESCollector)
    if es_collector is not None:
        population = es_collector.population_actor
        piece("es_forward", isinstance(population, PopulationActor), getattr(population, "actor", None) is not None and PopulationActor.refusal(population.actor) or None)
        backend = es_collector.backend
        name = getattr(backend, "worker_backend", backend.name)  # a Ray backend: what its workers run
        piece("es_physics", name == MujocoBatchBackend.name, es_collector.refusals[MujocoBatchBackend.name])
    return out


def implementation_line(implementations: dict[str, str]) -> str:
    """One line naming each piece's implementation (the run's start, ``summary.json``, the run log)."""
    return "pieces: " + ", ".join(f"{name} {what}" for name, what in implementations.items())
