"""The TD3 side's collector (paper, Algorithm 1 "act with exploration noise").

Two equal paths over the training env of :func:`torchrl_esrl.envs.make_env`, acting with the
exploration policy: TorchRL's ``Collector`` (the reference, :func:`make_td3_collector`) and
:class:`GymTD3Collector`, which steps the same gymnasium env directly. Both yield TensorDicts with
the replay buffer's transition keys and ``("next", "episode_reward")``;
:func:`make_frame_batches` picks one.
"""
from __future__ import annotations

from collections.abc import Collection

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictSequential
from torchrl.collectors import Collector
from torchrl.envs import GymWrapper, TransformedEnv
from torchrl.modules import AdditiveGaussianModule

from torchrl_esrl.envs import describe_transform, project_transforms
from torchrl_esrl.modules.networks import describe_actor, forward_difference, probe_observations, squash
from torchrl_esrl.modules.warmup import RandomWarmup
from torchrl_esrl.run.implementation import chosen_pieces
from torchrl_esrl.torchrl_private import collector_carrier, gym_env_of, gym_env_state, load_gym_env_state, restore_collector, unchecked_tensordict

_ACTIVATION_FUNCTIONS = {"tanh": torch.tanh, "relu": torch.relu, None: None}  # what each FAST_ACTIVATIONS module's forward computes


def make_td3_collector(env, td3, frames_per_batch: int = 1, device="cpu") -> Collector:
    """The reference: TorchRL's ``Collector`` acting with the exploration policy, for as long as it
    is iterated; the env steps on its own device (CPU physics) while the policy and the collected
    data are on ``device``."""
    return Collector(
        env,
        td3.exploration_policy,
        frames_per_batch=int(frames_per_batch),
        total_frames=-1,
        auto_register_policy_transforms=False,
        env_device=env.device,
        policy_device=device,
        storing_device=device,
    )


def _actor_layers(description) -> list:
    """``[(weight, bias or None, activation function or None), ...]`` of an actor's
    :func:`~torchrl_esrl.modules.networks.describe_actor` (Linear layers, each followed by at
    most one tanh or ReLU), with the Parameter objects themselves (TD3's optimiser and
    ``load_flat_parameters`` update them in place)."""
    return [(layer.linear.weight, layer.linear.bias, _ACTIVATION_FUNCTIONS[layer.activation]) for layer in description.mlp.layers]


def _actor_forward(layers, x: torch.Tensor) -> torch.Tensor:
    """The actor's MLP on ``x`` as its modules compute it (:func:`_actor_layers`), before ``TanhModule``."""
    for weight, bias, activation in layers:
        x = torch.nn.functional.linear(x, weight, bias)
        if activation is not None:
            x = activation(x)
    return x


def _forward_difference(actor, description) -> str | None:
    """Why :class:`GymTD3Collector`'s forward (one observation at a time) does not give the actor
    module's actions on the probe's observations (:func:`~torchrl_esrl.modules.networks.forward_difference`), or None."""
    layers, tanh_module = _actor_layers(description), description.tanh_module
    bounds = (tanh_module.action_low, tanh_module.action_high)

    def forward(observations: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return torch.cat([squash(tanh_module, _actor_forward(layers, row.unsqueeze(0)), *bounds) for row in observations])

    span = (bounds[1] - bounds[0]) if tanh_module.non_trivial else torch.tensor(2.0)
    return forward_difference(actor, {"the collector's forward": forward}, probe_observations(description.mlp.sizes[0][1]), span)


def _refusal(env, policy, device) -> str | None:
    """Why :class:`GymTD3Collector` cannot step exactly what ``Collector`` over ``env`` would, or
    None: decided from the env's transforms and the actor's description (its layers, and nothing
    run around them: :func:`~torchrl_esrl.modules.networks.describe_actor`), then by comparing the
    collector's forward with the actor module's own on a few observations."""
    if torch.device(device).type != "cpu" or (env.device is not None and torch.device(env.device).type != "cpu"):
        return f"the env and policy must be on cpu (got env {env.device}, policy {device})"
    if not isinstance(env, TransformedEnv) or not isinstance(env.base_env, GymWrapper):
        return f"the env must be a TransformedEnv over a gymnasium env (got {type(env).__name__})"
    if getattr(env.base_env, "frame_skip", 1) != 1:
        return f"frame_skip={env.base_env.frame_skip} (TorchRL's action repeat)"
    project = TransformedEnv(env.base_env, project_transforms())
    project.observation_spec  # noqa: B018 - resolves the transforms' keys, as the run's env has
    theirs, ours = describe_transform(env.transform), describe_transform(project.transform)
    if theirs != ours:
        names = [t[0].rpartition(".")[2] + ("" if t in ours[1] else "*") for t in theirs[1]] if theirs[0] == "Compose" else [theirs[0]]
        return f"env transforms {', '.join(names)} (* : not the project's DoubleToFloat, RewardSum, StepCounter as built)"
    inner = policy.policy if isinstance(policy, RandomWarmup) else policy
    if not isinstance(inner, TensorDictSequential) or len(inner.module) != 2 or type(inner.module[1]) is not AdditiveGaussianModule:
        return "the policy must be the actor followed by AdditiveGaussianModule"
    actor = inner.module[0]
    description = describe_actor(actor)
    return description if isinstance(description, str) else _forward_difference(actor, description)


class GymTD3Collector:
    """TD3's acting loop stepping the gymnasium env of a TorchRL ``GymEnv`` directly: the fast
    counterpart of TorchRL's ``Collector`` over ``TransformedEnv(GymEnv, DoubleToFloat, RewardSum,
    StepCounter)`` (:func:`make_td3_collector`).

    It does what that stack does for this env and this policy, in the same order:
    ``gym_env.reset()`` when an episode ends (no seed: the TorchRL env was seeded by
    ``set_seed``), the actor's MLP and ``TanhModule`` squashing, the ``AdditiveGaussianModule``
    draw (one standard normal draw per frame, the same RNG stream) projected on the action spec,
    float32 observations and rewards, and the float32 running episode return of ``RewardSum``.
    Each batch of ``frames_per_batch`` frames comes out as one TensorDict (tests/test_td3.py
    checks it against the ``Collector`` path, frame by frame). Any other env (another transform,
    another device) or policy (another layer or activation, a forward hook, a parametrization,
    a forward that gives other actions than the collector's on the probe's observations) is
    refused with a one-line error (:meth:`supports` says which are taken; the factory hands the
    others to ``Collector``).
    """

    @staticmethod
    def supports(env, td3, device="cpu") -> bool:
        return _refusal(env, td3.exploration_policy, device) is None

    def __init__(self, env, td3, frames_per_batch: int = 1):
        reason = _refusal(env, td3.exploration_policy, env.device or "cpu")
        if reason is not None:
            raise ValueError(f"GymTD3Collector steps exactly what TorchRL's Collector would only for make_env's env and make_actor's actor: {reason}")
        self.env = env
        self.gym_env = gym_env_of(env)
        self.frames_per_batch = int(frames_per_batch)
        self.device = env.device
        policy = td3.exploration_policy
        # Fujimoto's uniform warm-up (td3.random_frames) wraps the noisy actor: its draws, then the actor's.
        self.warmup = policy if isinstance(policy, RandomWarmup) else None
        actor, noise = (policy.policy if self.warmup is not None else policy)[:2]
        self.layers = _actor_layers(describe_actor(actor))
        self.tanh_module = actor[1]
        self.noise = noise
        # Buffers that load_state_dict overwrites in place: looked up once, as the layers are.
        self.squash_bounds = (self.tanh_module.action_low, self.tanh_module.action_high)
        self.action_spec = env.action_spec
        # Bounded.project is clamp(low, high) when out of the box and the identity inside: clamp.
        self.action_low, self.action_high = self.action_spec.space.low, self.action_spec.space.high
        # The elementwise steps after the actor's last tanh (TanhModule's affine map, the noise's
        # std, mean and scale, the sum, the clamp) on numpy views of the same float32 tensors, or None
        # where numpy would not compute exactly what torch does (another dtype or device, TanhModule's clamp).
        steps = (*self.squash_bounds, self.action_low, self.action_high, noise.sigma, noise.mean, noise.std)
        exact = not self.tanh_module.clamp and all(t.dtype == torch.float32 and t.device.type == "cpu" for t in steps)
        self.numpy_steps = tuple(t.detach().numpy() for t in steps) if exact else None
        self.observation_dim = env.observation_spec["observation"].shape[-1]
        self.action_dim = self.action_spec.shape[-1]
        self.observation: np.ndarray | None = None  # float64, as gymnasium returns it; None: reset next
        self.episode_reward = np.float32(0)
        self.frames = 0

    def __iter__(self):
        while True:
            yield self.next_batch()

    @torch.no_grad()
    def next_batch(self) -> TensorDict:
        n, gym_env = self.frames_per_batch, self.gym_env
        observations = np.empty((n, self.observation_dim), dtype=np.float32)
        next_observations = np.empty((n, self.observation_dim), dtype=np.float32)
        rewards = np.empty((n, 1), dtype=np.float32)
        terminated = np.empty((n, 1), dtype=bool)
        truncated = np.empty((n, 1), dtype=bool)
        episode_rewards = np.empty((n, 1), dtype=np.float32)
        actions = []  # one [1, action] tensor per frame
        tanh, noise, layers = self.tanh_module, self.noise, self.layers
        if self.numpy_steps is None:
            mean, std = noise.mean.expand(1, self.action_dim), noise.std.expand(1, self.action_dim)
        for i in range(n):
            if self.observation is None:
                self.observation = gym_env.reset()[0]
                self.episode_reward = np.float32(0)
            observations[i] = self.observation
            if self.warmup is not None and self.warmup.warming_up:
                action = self.warmup.draw((1,))
            else:
                x = _actor_forward(layers, torch.from_numpy(observations[i : i + 1]))
                if self.numpy_steps is None:
                    draw = torch.normal(mean=mean, std=std)  # AdditiveGaussianModule's draw
                    action = squash(tanh, x, *self.squash_bounds)
                    action = torch.clamp(action + draw * noise.sigma, self.action_low, self.action_high)
                else:
                    # squash() and the noise, the tanh by torch's kernel and the elementwise float32
                    # ops after it by numpy's, in torch's order: the same roundings (bit for bit,
                    # tests/test_td3.py), without torch's per-op dispatch on one row.
                    low, high, action_low, action_high, sigma, noise_mean, noise_std = self.numpy_steps
                    # ATen's normal(mean, std) is a standard normal draw, then * std + mean: the
                    # same generator stream and values as randn's draw scaled here.
                    draw = torch.randn(1, self.action_dim, dtype=torch.float32).numpy() * noise_std + noise_mean
                    squashed = low + (high - low) * (x.tanh().numpy() + 1) / 2
                    action = torch.from_numpy(np.clip(squashed + draw * sigma, action_low, action_high))
                if self.warmup is not None:
                    self.warmup.frames_acted += 1  # counted as RandomWarmup.forward counts them
            actions.append(action)
            observation, reward, term, trunc, _ = gym_env.step(action.numpy()[0])
            next_observations[i] = observation
            rewards[i, 0] = reward
            self.episode_reward = self.episode_reward + rewards[i, 0]
            episode_rewards[i, 0] = self.episode_reward
            terminated[i, 0], truncated[i, 0] = term, trunc
            self.observation = None if term or trunc else observation
        self.frames += n
        # Leaves built to fit (CPU, leading dim n): the constructor's per-leaf checks are skipped.
        return unchecked_tensordict(
            {
                "observation": torch.from_numpy(observations),
                "action": actions[0] if n == 1 else torch.cat(actions),
                "next": {
                    "observation": torch.from_numpy(next_observations),
                    "reward": torch.from_numpy(rewards),
                    "done": torch.from_numpy(terminated | truncated),
                    "terminated": torch.from_numpy(terminated),
                    "truncated": torch.from_numpy(truncated),
                    "episode_reward": torch.from_numpy(episode_rewards),
                },
            },
            torch.Size([n]),
            self.device,  # the buffers' storage device: TorchRL's writer then skips a .to() of every leaf
        )

    def state_dict(self) -> dict:
        return {
            "observation": None if self.observation is None else self.observation.copy(),
            "episode_reward": float(self.episode_reward),
            "frames": self.frames,
            "gym": gym_env_state(self.gym_env),
        }

    def load_state_dict(self, state: dict) -> None:
        observation = state["observation"]
        self.observation = None if observation is None else np.asarray(observation, dtype=np.float64)
        self.episode_reward = np.float32(state["episode_reward"])
        self.frames = int(state["frames"])
        load_gym_env_state(self.gym_env, state["gym"])

    def shutdown(self) -> None:
        """Nothing to stop (``Collector`` has threads/processes to end; this loop has none)."""


def finished_episode_returns(batch: TensorDictBase) -> list[float]:
    """Returns of the episodes that ended inside a collected batch (from TorchRL's ``RewardSum``)."""
    done = batch.get(("next", "done"))
    if done.numel() == 1 and not done.item():  # one frame, no episode end: no reshape and mask
        return []
    done = done.reshape(-1)
    if not done.any():
        return []
    return batch.get(("next", "episode_reward")).reshape(-1)[done].tolist()


class TD3EnvState:
    """The TD3 side's environment, as iterated by its collector across phases.

    :class:`GymTD3Collector` saves its own state (observation, running return, simulator).
    TorchRL's ``Collector.state_dict`` covers its counters and the transforms' buffers but not
    the carried tensordict nor the simulator, so both are saved here as well.
    """

    def __init__(self, collector):
        self.collector = collector

    def _gym_env(self):
        return gym_env_of(self.collector.env)

    def state_dict(self) -> dict:
        if isinstance(self.collector, GymTD3Collector):
            return {"gym_collector": self.collector.state_dict()}
        collector_state = {k: v for k, v in self.collector.state_dict().items() if k != "policy_state_dict"}  # policy: saved with TD3
        return {
            "collector": collector_state,
            "carrier": collector_carrier(self.collector).to_dict(),
            "gym": gym_env_state(self._gym_env()),
        }

    def load_state_dict(self, state: dict) -> None:
        if isinstance(self.collector, GymTD3Collector):
            self.collector.load_state_dict(state["gym_collector"])
            return
        collector = self.collector
        collector.env.transform.load_state_dict(state["collector"]["env_state_dict"])
        collector_state = state["collector"]
        carrier = TensorDict(state["carrier"], batch_size=collector_carrier(collector).batch_size)
        restore_collector(collector, collector_state["frames"], collector_state["iter"], carrier, collector_state.get("traj_pool"))  # absent: no pool saved
        load_gym_env_state(self._gym_env(), state["gym"])


def make_frame_batches(cfg, env, td3, pieces: Collection[str] | None = None):
    """The TD3 collector of a config and an iterator over it that lives across iterations:
    :class:`GymTD3Collector` where the ``td3_collector`` piece is chosen
    (:mod:`torchrl_esrl.run.implementation`) and it steps exactly what TorchRL's ``Collector``
    would (make_env's env, make_actor's actor), else the ``Collector``, ``td3.frames_per_batch``
    frames a batch."""
    if "td3_collector" in chosen_pieces(cfg, pieces) and GymTD3Collector.supports(env, td3, cfg.device):
        collector = GymTD3Collector(env, td3, cfg.td3.frames_per_batch)
    else:
        with torch.random.fork_rng():  # the Collector probes the policy once: its noise draw stays off the run's stream
            collector = make_td3_collector(env, td3, cfg.td3.frames_per_batch, device=cfg.device)
    if isinstance(td3.exploration_policy, RandomWarmup):
        td3.exploration_policy.reset()  # undo the Collector's probing call: the warm-up starts at frame 0
    return collector, iter(collector)
