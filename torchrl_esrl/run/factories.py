"""Small factories that turn the Hydra config (``conf/config.yaml``) into components.

Each one builds one thing of the paper from its section of the config, in the style of
TorchRL's ``sota-implementations``; recipes stay a readable transcription of Algorithm 1.
"""
from __future__ import annotations

import copy

import torch
from omegaconf import DictConfig

from torchrl_esrl.data.multibuffer import MultiBuffer
from torchrl_esrl.collectors.backends import default_backend
from torchrl_esrl.envs import make_env, resolve_env_id
from torchrl_esrl.es.openes import OpenES
from torchrl_esrl.collectors.es_collector import ESCollector
from torchrl_esrl.modules.networks import flat_parameters, make_actor, make_critic
from torchrl_esrl.algorithm.es_phase import ESPhase
from torchrl_esrl.modules.warmup import RandomWarmup
from torchrl_esrl.algorithm.overwrite import OverwriteRule
from torchrl_esrl.collectors.td3_collector import make_td3_collector
from torchrl_esrl.objectives.td3 import TD3
from torchrl_esrl.data.threshold import Threshold
from torchrl_esrl.threads import TD3_THREADS, job_cores


def make_train_env(cfg: DictConfig):
    return make_env(cfg.env.id, seed=cfg.seed, max_episode_steps=cfg.env.max_episode_steps)


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


def make_td3(cfg: DictConfig, actor, critic, action_spec) -> TD3:
    """TD3; with ``td3.random_frames`` > 0 its behaviour policy acts uniformly at random for that
    many frames first (Fujimoto's ``start_timesteps``, :class:`RandomWarmup`)."""
    c = cfg.td3
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
        fast=c.fast,
        num_threads=c.num_threads if c.num_threads is not None else min(TD3_THREADS, job_cores()),
    )
    if c.random_frames > 0:
        td3.exploration_policy = RandomWarmup(td3.exploration_policy, action_spec, c.random_frames, seed=int(cfg.seed) + 3)
    return td3


def make_td3_batches(cfg: DictConfig, env, td3: TD3):
    """The TD3 collector and an iterator over it that lives across iterations (``td3.fast``:
    :class:`~torchrl_esrl.collectors.td3_collector.GymTD3Collector`, else TorchRL's ``Collector``)."""
    collector = make_td3_collector(env, td3, cfg.td3.frames_per_batch, fast=cfg.td3.fast, device=cfg.device)
    if isinstance(td3.exploration_policy, RandomWarmup):
        td3.exploration_policy.reset()  # undo the Collector's probing call: the warm-up starts at frame 0
    return collector, iter(collector)


def make_multibuffer(cfg: DictConfig) -> MultiBuffer:
    """The good/bad/noisy MultiBuffer; ``buffer.mode=shared`` gives one buffer for everything
    (ERL-style ablation: ``ratio=(0, 0, 1)``, ES transitions are written to it too)."""
    c = cfg.buffer
    shared = c.mode == "shared"
    return MultiBuffer(
        ratio=[0.0, 0.0, 1.0] if shared else list(c.ratio),
        capacity=c.capacity,
        batch_size=c.batch_size,
        min_size=c.min_size,
        renormalize=c.renormalize,
        device=cfg.device,
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
    """CEM-RL's diagonal CEM (baseline, ``conf/cem_rl.yaml``) centred on the actor's parameters."""
    from torchrl_esrl.es.cem import DiagonalCEM

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


def make_es_collector(cfg: DictConfig, actor) -> ESCollector:
    """The ES collector on ``es.backend``; ``mujoco_batch`` steps on this job's share of the cores
    (:func:`~torchrl_esrl.threads.job_cores`)."""
    backend, backend_kwargs = cfg.es.backend, {}
    if backend == "auto":
        backend = default_backend(resolve_env_id(cfg.env.id))
    if backend == "ray":  # offspring evaluated on a Ray cluster, see the `ray` config section
        from torchrl_esrl.collectors.ray_backend import ray_backend_kwargs

        backend_kwargs = ray_backend_kwargs(cfg)
    elif backend == "mujoco_batch":
        backend_kwargs = {"nthread": job_cores()}
    return ESCollector(cfg.env.id, cpu_actor(actor), backend=backend, max_episode_steps=cfg.env.max_episode_steps, seed=int(cfg.seed) + 2, **backend_kwargs)


def make_threshold(cfg: DictConfig) -> Threshold:
    return Threshold(fraction=cfg.threshold.fraction)


def make_es_phase(cfg: DictConfig, es: OpenES, es_collector: ESCollector, buffer: MultiBuffer, threshold: Threshold, on_generation=None) -> ESPhase:
    """Algorithm 1's ES step; ``mode=async`` runs it in a thread alongside the TD3 phase."""
    return ESPhase(es, es_collector, buffer, threshold, cfg.es.generations_per_iteration, shared_buffer=cfg.buffer.mode == "shared", background=cfg.mode == "async", on_generation=on_generation)


def make_overwrite_rule(cfg: DictConfig) -> OverwriteRule:
    return OverwriteRule(window=cfg.overwrite.window, mode=cfg.overwrite.mode, mix=cfg.overwrite.mix)
