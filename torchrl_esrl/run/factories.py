"""Small factories that turn the Hydra config (``torchrl_esrl/run/schema.py``) into components.

Each one builds one thing of the paper from its section of the config, in the style of
TorchRL's ``sota-implementations``; recipes stay a readable transcription of Algorithm 1.

This module is the one reader of the ``implementation`` key: ``reference`` builds stock
TorchRL end to end (``TD3Loss`` with autograd, ``SoftUpdate``, ``torch.optim.Adam``, TorchRL's
``Collector`` over ``GymEnv``, the buffers' own ``extend`` and storage reads, and an ES
evaluation that runs the actor module through ``functional_call`` in gymnasium); ``fast``
swaps in the pieces of :data:`FAST_PIECES`, each a class beside the reference it replaces,
each proven equal to it (docs/performance.md). A fast piece that cannot compute exactly what
its reference would (another layer, transform or loss) hands over to the reference.
"""
from __future__ import annotations

import copy
import logging
import sys
from collections.abc import Collection

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.objectives import SoftUpdate, TD3Loss

from torchrl_esrl.data.multibuffer import MultiBuffer
from torchrl_esrl.envs import EnvSpec
from torchrl_esrl.es.openes import OpenES
from torchrl_esrl.collectors.backends import LOCAL_BACKENDS, resolve_backend
from torchrl_esrl.collectors.es_collector import ESCollector
from torchrl_esrl.modules.networks import ModulePopulation, PopulationActor, flat_parameters, make_actor, make_critic
from torchrl_esrl.algorithm.es_phase import ESPhase
from torchrl_esrl.modules.warmup import RandomWarmup
from torchrl_esrl.algorithm.overwrite import OverwriteRule
from torchrl_esrl.collectors.td3_collector import GymTD3Collector, make_td3_collector
from torchrl_esrl.objectives.td3 import TD3, ForeachSoftUpdate, ManualGradTD3Loss
from torchrl_esrl.data.threshold import Threshold
from torchrl_esrl.es.cem import DiagonalCEM
from torchrl_esrl.run.capacity import FLOAT, Holding, bytes_per_transition, mlp_parameters, network_holding, population_holdings
from torchrl_esrl.threads import job_cores

log = logging.getLogger(__name__)

IMPLEMENTATIONS = ("fast", "reference")
BF16_WARNING = (
    "warning: td3.precision=bf16 runs the TD3 actor's tanh squash in bfloat16, whose gradient is exactly 0 once the "
    "actor saturates, so the actor can stop learning: not for results (docs/deviations.md, 39)"
)
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
    ``implementation=fast``, none with ``implementation=reference``. Every factory below takes
    ``pieces`` (this, unless given: ``benchmarks.iteration --ablation`` switches one back)."""
    return frozenset(FAST_PIECES) if cfg.implementation == "fast" else frozenset()


def _pieces(cfg: DictConfig, pieces: Collection[str] | None) -> frozenset[str]:
    return fast_pieces(cfg) if pieces is None else frozenset(pieces)


def make_env_spec(cfg: DictConfig) -> EnvSpec:
    """The task as every part of the run plays it (``env``: id, kwargs, wrappers, transforms)."""
    return EnvSpec.from_config(cfg.env)


def make_train_env(cfg: DictConfig):
    """TD3's TorchRL env (:meth:`EnvSpec.make_torchrl`), seeded with the run's seed."""
    return make_env_spec(cfg).make_torchrl(seed=cfg.seed)


def make_actor_critic(cfg: DictConfig, env):
    """The paper's actor (2x256 tanh) and the critic template TD3 duplicates into twin critics,
    on ``cfg.device`` (TD3's side; ES evaluates populations on CPU, see :func:`cpu_actor`)."""
    observation_dim = env.observation_spec["observation"].shape[-1]
    action_dim = env.action_spec.shape[-1]
    actor = make_actor(observation_dim, env.action_spec, tuple(cfg.actor.hidden), cfg.actor.activation)
    critic = make_critic(observation_dim, action_dim, tuple(cfg.td3.critic_hidden), cfg.td3.critic_activation)
    return actor.to(cfg.device), critic.to(cfg.device)


def cpu_actor(actor):
    """``actor`` itself on CPU, else a CPU copy: the template of ES populations and evaluations,
    whose physics (and batched forward) run on CPU whatever device TD3 trains on."""
    if all(p.device.type == "cpu" for p in actor.parameters()):
        return actor
    return copy.deepcopy(actor).to("cpu")


def make_td3(cfg: DictConfig, actor, critic, action_spec, pieces: Collection[str] | None = None) -> TD3:
    """TD3; with ``td3.random_frames`` > 0 its behaviour policy acts uniformly at random for that
    many frames first (Fujimoto's ``start_timesteps``, :class:`RandomWarmup`)."""
    c, fast = cfg.td3, _pieces(cfg, pieces)
    td3 = TD3(
        actor,
        critic,
        action_spec.to(cfg.device),
        lr=c.lr,
        gamma=c.gamma,
        tau=c.tau,
        policy_noise=c.policy_noise,
        noise_clip=c.noise_clip,
        policy_delay=c.policy_delay,
        exploration_noise=c.exploration_noise,
        loss_function=c.loss_function,
        loss_class=ManualGradTD3Loss if "td3_loss" in fast else TD3Loss,  # it hands over to TD3Loss's autograd where it cannot compute exactly
        target_update_class=ForeachSoftUpdate if "soft_update" in fast else SoftUpdate,
        optimizer_impl="fused" if "adam" in fast else "default",
        num_threads=c.num_threads if c.num_threads is not None else job_cores(),
        precision=c.precision,
    )
    if c.precision == "bf16":
        log.warning(BF16_WARNING)
        print(BF16_WARNING, file=sys.stderr, flush=True)
    if c.random_frames > 0:
        td3.exploration_policy = RandomWarmup(td3.exploration_policy, action_spec, c.random_frames, seed=int(cfg.seed) + 3)
    return td3


def make_frame_batches(cfg: DictConfig, env, td3: TD3, pieces: Collection[str] | None = None):
    """The TD3 collector and an iterator over it that lives across iterations:
    :class:`~torchrl_esrl.collectors.td3_collector.GymTD3Collector` where it steps exactly what
    TorchRL's ``Collector`` would (make_env's env, make_actor's actor), else the ``Collector``."""
    if "td3_collector" in _pieces(cfg, pieces) and GymTD3Collector.supports(env, td3, cfg.device):
        collector = GymTD3Collector(env, td3, cfg.td3.frames_per_batch)
    else:
        with torch.random.fork_rng():  # the Collector probes the policy once: its noise draw stays off the run's stream
            collector = make_td3_collector(env, td3, cfg.td3.frames_per_batch, device=cfg.device)
    if isinstance(td3.exploration_policy, RandomWarmup):
        td3.exploration_policy.reset()  # undo the Collector's probing call: the warm-up starts at frame 0
    return collector, iter(collector)


def make_multibuffer(cfg: DictConfig, pieces: Collection[str] | None = None, one_buffer: bool = False) -> MultiBuffer:
    """The good/bad/noisy MultiBuffer; ``buffer.mode=shared`` gives one buffer for everything
    (ERL-style ablation: ``ratio=(0, 0, 1)``, ES transitions are written to it too), as does
    ``one_buffer`` (the TD3 and CEM-RL baselines' replay buffer)."""
    c, fast = cfg.buffer, _pieces(cfg, pieces)
    shared = one_buffer or c.mode == "shared"
    return MultiBuffer(
        ratio=[0.0, 0.0, 1.0] if shared else list(c.ratio),
        capacity=c.capacity,
        batch_size=c.batch_size,
        min_size=c.min_size,
        renormalize=c.renormalize and not one_buffer,
        device=cfg.device,
        direct_writes="buffer_writes" in fast,
        direct_reads="buffer_reads" in fast,
    )


def make_es(cfg: DictConfig, actor) -> OpenES:
    """OpenAI-ES whose mean starts at the (randomly initialised, near 0) actor's parameters."""
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


def make_cem(cfg: DictConfig, actor):
    """CEM-RL's diagonal CEM (baseline, the ``cem`` section) centred on the actor's parameters."""
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


def es_population(actor, pieces: Collection[str]):
    """The class that computes ES members' actions: :class:`PopulationActor` where it computes
    what ``actor`` does (tanh/ReLU MLPs, nothing run around their modules, the same actions on
    the probe's observations: :meth:`PopulationActor.refusal`), else the reference
    :class:`ModulePopulation`."""
    return PopulationActor if "es_forward" in pieces and PopulationActor.supports(actor) else ModulePopulation


def es_backend(cfg: DictConfig, pieces: Collection[str] | None = None, population_actor=None) -> tuple[str, dict]:
    """The ES collector's backend and its keyword arguments: ``es.backend`` (and, for ``ray``,
    ``ray.worker_backend``) resolved once (:func:`~torchrl_esrl.collectors.backends.resolve_backend`:
    ``auto`` is the fastest local backend for the env and the members' forward
    ``population_actor``, or the ``gym`` reference without the ``es_physics`` piece, which also
    refuses an explicit ``mujoco_batch``); ``mujoco_batch`` steps on this job's share of the cores
    (:func:`~torchrl_esrl.threads.job_cores`)."""
    spec, fast_physics = make_env_spec(cfg), "es_physics" in _pieces(cfg, pieces)
    backend = resolve_backend(cfg.es.backend, spec, fast_physics, population_actor=population_actor)
    if backend == "ray":  # offspring evaluated on a Ray cluster, see the `ray` config section
        kwargs = OmegaConf.to_container(cfg.ray, resolve=True)  # its keys are RayBackend's arguments
        kwargs["worker_backend"] = resolve_backend(kwargs["worker_backend"], spec, fast_physics, "ray.worker_backend", LOCAL_BACKENDS, population_actor)
        return backend, kwargs
    return backend, {"nthread": job_cores()} if backend == "mujoco_batch" else {}


def make_es_collector(cfg: DictConfig, actor, pieces: Collection[str] | None = None) -> ESCollector:
    """The ES collector on :func:`es_backend`."""
    fast = _pieces(cfg, pieces)
    actor = cpu_actor(actor)
    population = es_population(actor, fast)
    backend, backend_kwargs = es_backend(cfg, fast, population(actor))
    return ESCollector(
        make_env_spec(cfg), actor, backend=backend,
        seed=int(cfg.seed) + 2, population=population, **backend_kwargs,
    )


def make_evaluator(cfg: DictConfig, actor, pieces: Collection[str] | None = None) -> ESCollector:
    """The deterministic evaluation of a recipe's policies: ``actor``'s architecture played in
    gymnasium (the ``gym`` backend), on the evaluation seed stream."""
    actor = cpu_actor(actor)
    population = es_population(actor, _pieces(cfg, pieces))
    return ESCollector(make_env_spec(cfg), actor, backend="gym", seed=int(cfg.seed) + 1000, population=population)


# ------------------------------------------------------------ what each component will hold
# (the recipe's ``holdings``: the run's memory and disk estimate, torchrl_esrl/run/capacity.py)
NETWORK_FIELD = "actor.hidden or td3.critic_hidden"


def _actor_parameters(cfg: DictConfig, sizes) -> int:
    return mlp_parameters([sizes.observation_dim, *cfg.actor.hidden, sizes.action_dim])


def buffer_holdings(cfg: DictConfig, sizes, buffers: int) -> list[Holding]:
    """``buffers`` replay buffers of ``buffer.capacity`` transitions each (:func:`make_multibuffer`
    with its three buffers, or ``buffers=1`` with one), on ``device``."""
    size = buffers * int(cfg.buffer.capacity) * bytes_per_transition(sizes.observation_dim, sizes.action_dim)
    return [Holding("buffers", size, "buffer.capacity", on_device=True)]


def td3_holdings(cfg: DictConfig, sizes) -> list[Holding]:
    """:func:`make_td3`'s networks and optimiser states (:attr:`TD3.HELD_ACTOR_COPIES`, ...)."""
    critic = mlp_parameters([sizes.observation_dim + sizes.action_dim, *cfg.td3.critic_hidden, 1])
    return [network_holding(TD3.HELD_ACTOR_COPIES, _actor_parameters(cfg, sizes), NETWORK_FIELD), network_holding(TD3.HELD_CRITIC_COPIES, critic, NETWORK_FIELD)]


def _strategy_holdings(cfg: DictConfig, sizes, section: str, copies: int) -> list[Holding]:
    c, parameters = cfg[section], _actor_parameters(cfg, sizes)
    transition = bytes_per_transition(sizes.observation_dim, sizes.action_dim)
    field = f"{section}.population_size"
    return [network_holding(copies, parameters, NETWORK_FIELD), *population_holdings(parameters, int(c.population_size), bool(c.antithetic), sizes.episode_steps, transition, field)]


def es_holdings(cfg: DictConfig, sizes) -> list[Holding]:
    """:func:`make_es`'s OpenAI-ES state and one generation (population, noise, episodes)."""
    return _strategy_holdings(cfg, sizes, "es", OpenES.HELD_COPIES)


def cem_holdings(cfg: DictConfig, sizes) -> list[Holding]:
    """:func:`make_cem`'s CEM state and one generation (population, noise, episodes); a stop
    within the generation's gradient steps also writes its population to the checkpoint."""
    population = Holding("population", FLOAT * _actor_parameters(cfg, sizes) * int(cfg.cem.population_size), "cem.population_size", in_memory=False)
    return [*_strategy_holdings(cfg, sizes, "cem", DiagonalCEM.HELD_COPIES), population]


def make_threshold(cfg: DictConfig) -> Threshold:
    return Threshold(fraction=cfg.threshold.fraction)


def make_es_phase(cfg: DictConfig, es: OpenES, es_collector: ESCollector, buffer: MultiBuffer, threshold: Threshold, on_generation=None) -> ESPhase:
    """Algorithm 1's ES step; ``es.schedule=async`` runs it in a thread alongside the TD3 phase."""
    return ESPhase(es, es_collector, buffer, threshold, cfg.es.generations_per_iteration, shared_buffer=cfg.buffer.mode == "shared", background=cfg.es.schedule == "async", on_generation=on_generation)


def make_overwrite_rule(cfg: DictConfig) -> OverwriteRule:
    return OverwriteRule(window=cfg.overwrite.window, mode=cfg.overwrite.mode, mix=cfg.overwrite.mix)


def component(components: dict, kind: type):
    """The first of a recipe's ``components`` (name -> object, as given to ``Run.start``) that is a
    ``kind``, or None: the run plumbing finds a component by what it is, not by its name."""
    return next((value for value in components.values() if isinstance(value, kind)), None)


def implementations(cfg: DictConfig, **components) -> dict[str, str]:
    """What computes each piece of :data:`FAST_PIECES` in this run: ``fast``, ``reference``, or
    ``reference (why)`` where ``implementation=fast`` asked for the fast piece and it handed over
    (``es_physics: reference (env.wrappers: ClipReward)``). ``components`` are the recipe's, found
    by what they are, whatever the recipe calls them (a :class:`TD3`, a ``TD3EnvState``, a
    :class:`MultiBuffer`, an :class:`ESCollector`; others are ignored); a piece the run does not
    have is left out."""
    from torchrl_esrl.collectors.mujoco_batch import MujocoBatchBackend
    from torchrl_esrl.collectors.td3_collector import TD3EnvState, _refusal

    asked = fast_pieces(cfg)

    def piece(name: str, fast: bool, why: str | None = None) -> None:
        if fast:
            out[name] = "fast"
        elif name in asked:
            out[name] = f"reference ({why})" if why else "reference"
        else:
            out[name] = "reference"

    out: dict[str, str] = {}
    td3 = component(components, TD3)
    if td3 is not None:
        loss = td3.loss
        refusal = getattr(loss, "refusal", None)
        why = refusal() if callable(refusal) else None
        piece("td3_loss", isinstance(loss, ManualGradTD3Loss) and why is None, why)
        piece("soft_update", isinstance(td3.target_update, ForeachSoftUpdate))
        piece("adam", td3.optimizer_impl == "fused")
    td3_env = component(components, TD3EnvState)
    if td3_env is not None:
        collector = td3_env.collector
        fast = isinstance(collector, GymTD3Collector)
        piece("td3_collector", fast, None if fast or td3 is None else _refusal(collector.env, td3.exploration_policy, cfg.device))
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
