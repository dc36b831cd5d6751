"""TorchRL's stock TD3 pieces assembled as TorchRL's ``sota-implementations/td3`` example assembles them
(``td3.py`` and ``utils.py``): the peer ``torchrl_stock`` of :mod:`benchmarks.peers`.

The env: ``ParallelEnv(1, EnvCreator(GymEnv), serial_for_single=True)`` (a ``SerialEnv`` of one env)
under ``StepCounter(max_steps)``, ``InitTracker``, ``DoubleToFloat``, ``RewardSum``. The actor: an
``MLP`` in a ``TensorDictModule`` then ``TanhModule``, explored by ``AdditiveGaussianModule``
(sigma 1, std = the exploration noise); the critic: an ``MLP`` in a ``ValueOperator``. ``TD3Loss``
(twin critics, delayed actor and critics), ``SoftUpdate``, one ``torch.optim.Adam`` per side.
``Collector`` (the 0.14 name of ``SyncDataCollector``) with ``init_random_frames``; a
``TensorDictReplayBuffer`` over ``LazyTensorStorage`` with ``prefetch=3``: the example's storage
for its default ``replay_buffer.scratch_dir`` (empty); its earlier versions made a temporary
directory there and used ``LazyMemmapStorage``. The loop body is the example's per collected batch
(weights sync, ``extend``, ``num_updates`` updates each sampling the buffer, the delayed actor and
target update, the episode-end lookup) without its logging, evaluation and timers.

Where this departs from the example's config: one frame per batch (Algorithm 1: one update after
each env step; the example collects 1,000), the hidden activations of the paper (actor tanh,
critics ReLU; the example's are ReLU), Adam's default ``eps`` (the example sets 1e-4; the same
arithmetic), and no ``torch.set_float32_matmul_precision("high")`` (process-wide: it would act on
the other implementations timed beside it).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn, optim
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import Compose, DoubleToFloat, EnvCreator, InitTracker, ParallelEnv, RewardSum, StepCounter, TransformedEnv
from torchrl.envs.libs.gym import GymEnv, set_gym_backend
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, AdditiveGaussianModule, TanhModule, ValueOperator
from torchrl.objectives import SoftUpdate
from torchrl.objectives.td3 import TD3Loss


@dataclass
class Config:
    env_id: str
    seed: int
    max_episode_steps: int
    init_random_frames: int
    frames_per_batch: int
    buffer_size: int
    batch_size: int
    prefetch: int
    lr: float
    gamma: float
    tau: float
    policy_noise: float
    noise_clip: float
    policy_update_delay: int
    utd_ratio: float
    exploration_noise: float
    actor_hidden: tuple[int, ...]
    critic_hidden: tuple[int, ...]
    actor_activation: type[nn.Module]  # the example's: nn.ReLU
    critic_activation: type[nn.Module]


def env_maker(env_id: str, device="cpu"):
    with set_gym_backend("gymnasium"):
        return GymEnv(env_id, device=device)


def make_environment(cfg: Config, device) -> TransformedEnv:
    parallel_env = ParallelEnv(1, EnvCreator(functools.partial(env_maker, cfg.env_id)), serial_for_single=True, device=device)
    parallel_env.set_seed(cfg.seed)
    return TransformedEnv(parallel_env, Compose(StepCounter(max_steps=cfg.max_episode_steps), InitTracker(), DoubleToFloat(), RewardSum()))


def make_td3_agent(cfg: Config, train_env, device):
    action_spec = train_env.action_spec_unbatched.to(device)
    actor_net = MLP(num_cells=list(cfg.actor_hidden), out_features=action_spec.shape[-1], activation_class=cfg.actor_activation, device=device)
    actor = TensorDictSequential(
        TensorDictModule(actor_net, in_keys=["observation"], out_keys=["param"]),
        TanhModule(in_keys=["param"], out_keys=["action"], spec=action_spec),
    )
    qvalue_net = MLP(num_cells=list(cfg.critic_hidden), out_features=1, activation_class=cfg.critic_activation, device=device)
    qvalue = ValueOperator(in_keys=["action", "observation"], module=qvalue_net)
    model = nn.ModuleList([actor, qvalue])
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):  # initialises the lazy layers
        td = train_env.fake_tensordict().to(device)
        for net in model:
            net(td)
    explore = TensorDictSequential(
        actor,
        AdditiveGaussianModule(sigma_init=1.0, sigma_end=1.0, mean=0.0, std=cfg.exploration_noise, spec=action_spec, device=device),
    )
    return model, explore


def make_loss_module(cfg: Config, model):
    loss_module = TD3Loss(
        actor_network=model[0],
        qvalue_network=model[1],
        num_qvalue_nets=2,
        loss_function="l2",
        delay_actor=True,
        delay_qvalue=True,
        action_spec=model[0][1].spec,
        policy_noise=cfg.policy_noise,
        noise_clip=cfg.noise_clip,
    )
    loss_module.make_value_estimator(gamma=cfg.gamma)
    return loss_module, SoftUpdate(loss_module, eps=1 - cfg.tau)


def make_optimizer(cfg: Config, loss_module):
    critic_params = list(loss_module.qvalue_network_params.flatten_keys().values())
    actor_params = list(loss_module.actor_network_params.flatten_keys().values())
    return optim.Adam(actor_params, lr=cfg.lr), optim.Adam(critic_params, lr=cfg.lr)


class TorchRLStockTD3:
    """The example's setup; :meth:`steps` is its loop, one collected batch per ``next()``."""

    def __init__(self, cfg: Config):
        self.cfg = cfg
        device = self.device = torch.device("cpu")
        torch.manual_seed(cfg.seed)
        self.train_env = make_environment(cfg, device)
        self.model, self.exploration_policy = make_td3_agent(cfg, self.train_env, device)
        self.loss_module, self.target_net_updater = make_loss_module(cfg, self.model)
        self.collector = Collector(
            self.train_env,
            self.exploration_policy,
            init_random_frames=cfg.init_random_frames,
            frames_per_batch=cfg.frames_per_batch,
            total_frames=-1,
            reset_at_each_iter=False,
            device=device,
        )
        self.collector.set_seed(cfg.seed)
        self.replay_buffer = TensorDictReplayBuffer(
            pin_memory=False, prefetch=cfg.prefetch, storage=LazyTensorStorage(cfg.buffer_size, device=device), batch_size=cfg.batch_size
        )
        self.optimizer_actor, self.optimizer_critic = make_optimizer(cfg, self.loss_module)
        self.q_loss: torch.Tensor | None = None  # the last update's critic loss

    def update(self, sampled_tensordict, update_actor: bool):
        q_loss, *_ = self.loss_module.value_loss(sampled_tensordict)
        q_loss.backward()
        self.optimizer_critic.step()
        self.optimizer_critic.zero_grad(set_to_none=True)
        if update_actor:
            actor_loss, *_ = self.loss_module.actor_loss(sampled_tensordict)
            actor_loss.backward()
            self.optimizer_actor.step()
            self.optimizer_actor.zero_grad(set_to_none=True)
            self.target_net_updater.step()
        else:
            actor_loss = q_loss.new_zeros(())
        return q_loss.detach(), actor_loss.detach()

    def steps(self):
        """The example's loop: each ``next()`` collects one batch, stores it and, once
        ``init_random_frames`` are collected, makes its updates."""
        cfg, collector, replay_buffer = self.cfg, self.collector, self.replay_buffer
        num_updates = int(cfg.frames_per_batch * cfg.utd_ratio)
        collected_frames, update_counter = 0, 0
        collector_iter = iter(collector)
        while True:
            tensordict = next(collector_iter)
            collector.update_policy_weights_()
            current_frames = tensordict.numel()
            tensordict = tensordict.reshape(-1)
            replay_buffer.extend(tensordict)
            collected_frames += current_frames
            if collected_frames >= cfg.init_random_frames:
                q_losses = []
                for _ in range(num_updates):
                    update_counter += 1
                    update_actor = update_counter % cfg.policy_update_delay == 0
                    sampled_tensordict = replay_buffer.sample()
                    q_loss, actor_loss = self.update(sampled_tensordict, update_actor)
                    q_losses.append(q_loss.clone())
                self.q_loss = q_losses[-1]
            episode_end = tensordict["next", "done"] if tensordict["next", "done"].any() else tensordict["next", "truncated"]
            tensordict["next", "episode_reward"][episode_end]  # the example's episode-end lookup (for its log)
            yield collected_frames

    def shutdown(self) -> None:
        self.collector.shutdown()
        if not self.train_env.is_closed:
            self.train_env.close()
