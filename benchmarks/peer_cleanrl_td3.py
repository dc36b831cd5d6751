"""A plain single-file TD3 (Fujimoto et al. 2018) in the style of CleanRL's ``td3_continuous_action.py``:
the peer ``cleanrl_style`` of :mod:`benchmarks.peers`.

Written here after that program's structure: a gymnasium ``SyncVectorEnv`` of one env with
``RecordEpisodeStatistics``, eager PyTorch networks, ``torch.optim.Adam``, a numpy replay buffer
sampled uniformly (after Stable-Baselines3's, which CleanRL uses), numpy -> torch conversions at every
step, a per-parameter loop for the soft update, and one loop over global steps: uniform random
actions for ``learning_starts`` steps, then the actor with Gaussian exploration noise, one update per
step. Two changes, each stated where it is made: the actor's hidden activation is a parameter (the
paper's actor is tanh, CleanRL's ReLU), and the env autoresets in the same step (gymnasium 1.x
removed the ``final_observation`` CleanRL reads; ``SAME_STEP`` gives it back as ``final_obs``).
"""
from __future__ import annotations

import random
from dataclasses import dataclass
from typing import NamedTuple

import gymnasium as gym
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn, optim


@dataclass
class Args:
    env_id: str
    seed: int
    buffer_size: int
    learning_rate: float
    gamma: float
    tau: float
    batch_size: int
    policy_noise: float
    exploration_noise: float
    learning_starts: int
    policy_frequency: int
    noise_clip: float
    actor_hidden: tuple[int, ...]
    critic_hidden: tuple[int, ...]
    actor_activation: type[nn.Module]  # CleanRL's actor: nn.ReLU
    critic_activation: type[nn.Module]


def make_env(env_id: str, seed: int):
    def thunk():
        env = gym.make(env_id)
        env = gym.wrappers.RecordEpisodeStatistics(env)
        env.action_space.seed(seed)
        return env

    return thunk


def mlp(sizes, activation) -> nn.Sequential:
    layers = []
    for i, (inputs, outputs) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(inputs, outputs))
        if i < len(sizes) - 2:
            layers.append(activation())
    return nn.Sequential(*layers)


class QNetwork(nn.Module):
    def __init__(self, envs, hidden, activation):
        super().__init__()
        inputs = int(np.prod(envs.single_observation_space.shape) + np.prod(envs.single_action_space.shape))
        self.net = mlp([inputs, *hidden, 1], activation)

    def forward(self, x, a):
        return self.net(torch.cat([x, a], 1))


class Actor(nn.Module):
    def __init__(self, envs, hidden, activation):
        super().__init__()
        space = envs.single_action_space
        self.net = mlp([int(np.prod(envs.single_observation_space.shape)), *hidden, int(np.prod(space.shape))], activation)
        self.register_buffer("action_scale", torch.tensor((space.high - space.low) / 2.0, dtype=torch.float32))
        self.register_buffer("action_bias", torch.tensor((space.high + space.low) / 2.0, dtype=torch.float32))

    def forward(self, x):
        return torch.tanh(self.net(x)) * self.action_scale + self.action_bias


class ReplayBufferSamples(NamedTuple):
    observations: torch.Tensor
    actions: torch.Tensor
    next_observations: torch.Tensor
    dones: torch.Tensor
    rewards: torch.Tensor


class ReplayBuffer:
    """Preallocated numpy arrays (buffer_size, n_envs, ...), written in a ring, sampled uniformly
    among the items written, each sample copied into new torch tensors."""

    def __init__(self, buffer_size: int, observation_space, action_space, device, n_envs: int = 1):
        self.buffer_size, self.n_envs, self.device = buffer_size, n_envs, device
        self.observations = np.zeros((buffer_size, n_envs, *observation_space.shape), dtype=observation_space.dtype)
        self.next_observations = np.zeros((buffer_size, n_envs, *observation_space.shape), dtype=observation_space.dtype)
        self.actions = np.zeros((buffer_size, n_envs, *action_space.shape), dtype=action_space.dtype)
        self.rewards = np.zeros((buffer_size, n_envs), dtype=np.float32)
        self.dones = np.zeros((buffer_size, n_envs), dtype=np.float32)
        self.timeouts = np.zeros((buffer_size, n_envs), dtype=np.float32)  # stays zero: no timeout handling, as CleanRL asks
        self.pos, self.full = 0, False

    def add(self, obs, next_obs, action, reward, done, infos) -> None:
        self.observations[self.pos] = np.array(obs)
        self.next_observations[self.pos] = np.array(next_obs)
        self.actions[self.pos] = np.array(action)
        self.rewards[self.pos] = np.array(reward)
        self.dones[self.pos] = np.array(done)
        self.pos += 1
        if self.pos == self.buffer_size:
            self.full, self.pos = True, 0

    def sample(self, batch_size: int) -> ReplayBufferSamples:
        upper_bound = self.buffer_size if self.full else self.pos
        batch_inds = np.random.randint(0, upper_bound, size=batch_size)
        env_indices = np.random.randint(0, high=self.n_envs, size=(len(batch_inds),))
        data = (
            self.observations[batch_inds, env_indices, :],
            self.actions[batch_inds, env_indices, :],
            self.next_observations[batch_inds, env_indices, :],
            (self.dones[batch_inds, env_indices] * (1 - self.timeouts[batch_inds, env_indices])).reshape(-1, 1),
            self.rewards[batch_inds, env_indices].reshape(-1, 1),
        )
        return ReplayBufferSamples(*(torch.tensor(array, device=self.device) for array in data))


class CleanRLStyleTD3:
    """The program's setup; :meth:`steps` is its training loop, one global step per ``next()``."""

    def __init__(self, args: Args):
        self.args = args
        random.seed(args.seed)
        np.random.seed(args.seed)
        torch.manual_seed(args.seed)
        self.device = torch.device("cpu")
        # SAME_STEP: the final observation of an episode comes in infos["final_obs"] (gymnasium 1.x)
        self.envs = gym.vector.SyncVectorEnv([make_env(args.env_id, args.seed)], autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
        envs = self.envs
        assert isinstance(envs.single_action_space, gym.spaces.Box), "only continuous action space is supported"
        self.actor = Actor(envs, args.actor_hidden, args.actor_activation).to(self.device)
        self.qf1 = QNetwork(envs, args.critic_hidden, args.critic_activation).to(self.device)
        self.qf2 = QNetwork(envs, args.critic_hidden, args.critic_activation).to(self.device)
        self.qf1_target = QNetwork(envs, args.critic_hidden, args.critic_activation).to(self.device)
        self.qf2_target = QNetwork(envs, args.critic_hidden, args.critic_activation).to(self.device)
        self.target_actor = Actor(envs, args.actor_hidden, args.actor_activation).to(self.device)
        self.target_actor.load_state_dict(self.actor.state_dict())
        self.qf1_target.load_state_dict(self.qf1.state_dict())
        self.qf2_target.load_state_dict(self.qf2.state_dict())
        self.q_optimizer = optim.Adam(list(self.qf1.parameters()) + list(self.qf2.parameters()), lr=args.learning_rate)
        self.actor_optimizer = optim.Adam(list(self.actor.parameters()), lr=args.learning_rate)
        # float32 observations in the buffer (CleanRL sets the env's own space's dtype, which makes gymnasium's checker warn)
        space = envs.single_observation_space
        self.rb = ReplayBuffer(args.buffer_size, gym.spaces.Box(space.low.astype(np.float32), space.high.astype(np.float32), space.shape, np.float32), envs.single_action_space, self.device, n_envs=1)
        self.qf_loss: torch.Tensor | None = None  # the last update's critic loss

    def steps(self):
        """The training loop: each ``next()`` plays one global step (and its update once learning has started)."""
        args, envs, rb, device = self.args, self.envs, self.rb, self.device
        actor, qf1, qf2, target_actor, qf1_target, qf2_target = self.actor, self.qf1, self.qf2, self.target_actor, self.qf1_target, self.qf2_target
        q_optimizer, actor_optimizer = self.q_optimizer, self.actor_optimizer
        obs, _ = envs.reset(seed=args.seed)
        global_step = 0
        while True:
            if global_step < args.learning_starts:
                actions = np.array([envs.single_action_space.sample() for _ in range(envs.num_envs)])
            else:
                with torch.no_grad():
                    actions = actor(torch.Tensor(obs).to(device))
                    actions += torch.normal(0, actor.action_scale * args.exploration_noise)
                    actions = actions.cpu().numpy().clip(envs.single_action_space.low, envs.single_action_space.high)

            next_obs, rewards, terminations, truncations, infos = envs.step(actions)
            if "final_info" in infos:  # CleanRL logs the finished episodes' returns here
                pass

            real_next_obs = next_obs.copy()
            for idx, trunc in enumerate(truncations):
                if trunc:
                    real_next_obs[idx] = infos["final_obs"][idx]
            rb.add(obs, real_next_obs, actions, rewards, terminations, infos)
            obs = next_obs

            if global_step > args.learning_starts:
                data = rb.sample(args.batch_size)
                with torch.no_grad():
                    clipped_noise = (torch.randn_like(data.actions, device=device) * args.policy_noise).clamp(
                        -args.noise_clip, args.noise_clip
                    ) * target_actor.action_scale
                    next_state_actions = (target_actor(data.next_observations) + clipped_noise).clamp(
                        envs.single_action_space.low[0], envs.single_action_space.high[0]
                    )
                    qf1_next_target = qf1_target(data.next_observations, next_state_actions)
                    qf2_next_target = qf2_target(data.next_observations, next_state_actions)
                    min_qf_next_target = torch.min(qf1_next_target, qf2_next_target)
                    next_q_value = data.rewards.flatten() + (1 - data.dones.flatten()) * args.gamma * min_qf_next_target.view(-1)

                qf1_a_values = qf1(data.observations, data.actions).view(-1)
                qf2_a_values = qf2(data.observations, data.actions).view(-1)
                qf_loss = F.mse_loss(qf1_a_values, next_q_value) + F.mse_loss(qf2_a_values, next_q_value)
                q_optimizer.zero_grad()
                qf_loss.backward()
                q_optimizer.step()
                self.qf_loss = qf_loss.detach()

                if global_step % args.policy_frequency == 0:
                    actor_loss = -qf1(data.observations, actor(data.observations)).mean()
                    actor_optimizer.zero_grad()
                    actor_loss.backward()
                    actor_optimizer.step()
                    for network, target in ((actor, target_actor), (qf1, qf1_target), (qf2, qf2_target)):
                        for param, target_param in zip(network.parameters(), target.parameters()):
                            target_param.data.copy_(args.tau * param.data + (1 - args.tau) * target_param.data)
            global_step += 1
            yield global_step
