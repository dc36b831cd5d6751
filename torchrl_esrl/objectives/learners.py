"""The learners a recipe's TD3 phase can run (``learner=td3|ddpg|sac``), built from the config.

A recipe that offers the choice declares the ``learner`` section (``recipe_main(...,
sections={"learner": LearnerConfig})``) and lists the ``learner`` config group in its defaults
(``- learner: td3``; ``conf/learner/<name>.yaml`` sets ``learner.name``). The section holds DDPG's
and SAC's own hyper-parameters (``learner.sac.alpha_init=0.2``); every learner reads the ``td3``
section's phase keys (frames per iteration and per batch, updates per frame, ``random_frames``,
``num_threads``) and critic layers; TD3's own hyper-parameters stay TD3's (docs/deviations.md).
"""
from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass, field

from omegaconf import DictConfig

from torchrl_esrl.errors import ConfigError
from torchrl_esrl.modules.networks import NETWORK_FIELD, make_actor_critic, make_critic
from torchrl_esrl.modules.warmup import RandomWarmup
from torchrl_esrl.objectives.ddpg import DDPG, DDPGConfig
from torchrl_esrl.objectives.learner import Learner
from torchrl_esrl.objectives.sac import SAC, SACConfig, make_sac_actor
from torchrl_esrl.objectives.td3 import make_td3, td3_holdings
from torchrl_esrl.run.capacity import Holding, mlp_parameters, network_holding
from torchrl_esrl.run.schema import one_of
from torchrl_esrl.threads import job_cores

LEARNERS = {"td3": "TD3", "ddpg": "DDPG", "sac": "SAC"}  # learner= name -> its name in labels


@dataclass
class LearnerConfig:
    """The ``learner`` section: which learner the TD3 phase runs, and DDPG's and SAC's values."""

    name: str = one_of("td3", among="torchrl_esrl.objectives.learners.LEARNERS")  # conf/learner/<name>.yaml sets it: learner=ddpg
    ddpg: DDPGConfig = field(default_factory=DDPGConfig)  # read with learner=ddpg
    sac: SACConfig = field(default_factory=SACConfig)  # read with learner=sac


def make_learner(cfg: DictConfig, env, pieces: Collection[str] | None = None) -> Learner:
    """``cfg.learner.name``'s learner with its networks (the ``actor`` section's actor, critics of
    ``td3.critic_hidden``) on ``cfg.device`` for ``env``'s task. TD3 is :func:`make_td3`'s, with
    the fast pieces of ``pieces``; DDPG and SAC run the stock TorchRL path. With
    ``td3.random_frames`` > 0 the behaviour policy first acts uniformly at random
    (:class:`RandomWarmup`), whatever the learner."""
    name = cfg.learner.name
    if name == "td3":
        actor, critic = make_actor_critic(cfg, env)
        return make_td3(cfg, actor, critic, env.action_spec, pieces)
    action_spec = env.action_spec.to(cfg.device)
    threads = cfg.td3.num_threads if cfg.td3.num_threads is not None else job_cores()
    if name == "ddpg":
        actor, critic = make_actor_critic(cfg, env)
        learner = DDPG(actor, critic, action_spec, **cfg.learner.ddpg, num_threads=threads)
    else:
        observation_dim = env.observation_spec["observation"].shape[-1]
        policy, actor = make_sac_actor(observation_dim, action_spec, tuple(cfg.actor.hidden), cfg.actor.activation)
        critic = make_critic(observation_dim, env.action_spec.shape[-1], tuple(cfg.td3.critic_hidden), cfg.td3.critic_activation)
        learner = SAC(policy.to(cfg.device), actor.to(cfg.device), critic.to(cfg.device), action_spec, **cfg.learner.sac, num_threads=threads)
    if cfg.td3.random_frames > 0:
        learner.exploration_policy = RandomWarmup(learner.exploration_policy, env.action_spec, cfg.td3.random_frames, seed=int(cfg.seed) + 3)
    return learner


def learner_holdings(cfg: DictConfig, sizes) -> list[Holding]:
    """What :func:`make_learner` builds, for the run's memory estimate (:mod:`torchrl_esrl.run.capacity`):
    the learner's networks and optimiser states. Run before any work, it also refuses what only
    TD3 computes (``td3.precision=bf16``) for another learner."""
    name = cfg.learner.name
    if name == "td3":
        return td3_holdings(cfg, sizes)
    if cfg.td3.precision != "fp32":
        raise ConfigError(f"td3.precision: {cfg.td3.precision!r} is TD3's alone (allowed: fp32 with learner.name={name})")
    learner = {"ddpg": DDPG, "sac": SAC}[name]
    critic = mlp_parameters([sizes.observation_dim + sizes.action_dim, *cfg.td3.critic_hidden, 1])
    return [network_holding(learner.HELD_ACTOR_COPIES, learner.policy_parameters(cfg.actor.hidden, sizes), NETWORK_FIELD), network_holding(learner.HELD_CRITIC_COPIES, critic, NETWORK_FIELD)]
