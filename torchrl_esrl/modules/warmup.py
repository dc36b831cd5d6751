"""Uniform-random warm-up of a TD3 behaviour policy (Fujimoto et al. 2018, ``start_timesteps``).

Fujimoto's TD3 acts uniformly at random in the action box for its first 25,000 steps, then with
the actor plus Gaussian exploration noise. :class:`RandomWarmup` is that switch as a TorchRL
policy module: it sits where the exploration policy sits (``td3.exploration_policy``), so any
collector that calls a policy per step uses it unchanged. ``td3.random_frames`` sets the length
(``torchrl_esrl/run/schema.py``: K, 25,000 at the paper's K, for the TD3 baseline; 0 for ES-TD3Buffers,
whose Algorithm 1 acts with the noisy actor from the first step; docs/deviations.md).
"""
from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase


class RandomWarmup(TensorDictModuleBase):
    """Uniform actions in ``action_spec``'s box for the first ``frames`` frames, then ``policy``.

    The random actions come from a generator of their own (seeded by ``seed``); the frames acted
    so far and that generator's state are part of ``state_dict``, so a restored run continues the
    warm-up exactly where it stopped.
    """

    def __init__(self, policy, action_spec, frames: int, seed: int, action_key="action"):
        super().__init__()
        self.policy = policy
        self.in_keys = list(policy.in_keys)
        self.out_keys = [action_key]
        self.action_key = action_key
        self.seed = int(seed)
        device = next(policy.parameters(), torch.empty(0)).device  # the policy's: TorchRL's Collector steps a policy wholly on its device itself, and a copy of any other
        self.register_buffer("low", action_spec.space.low.clone().float().to(device))
        self.register_buffer("high", action_spec.space.high.clone().float().to(device))
        self.frames = int(frames)
        self.generator = torch.Generator()
        self.reset()

    def reset(self) -> None:
        """Start the warm-up over: no frame acted, the generator at its seed. TorchRL's
        ``Collector`` calls its policy once when it is built, to learn the policy's outputs;
        :func:`~torchrl_esrl.collectors.td3_collector.make_frame_batches` resets after that call."""
        self.frames_acted = 0
        self.generator.manual_seed(self.seed)

    @property
    def warming_up(self) -> bool:
        return self.frames_acted < self.frames

    def draw(self, batch_shape: tuple[int, ...]) -> torch.Tensor:
        """Uniform actions for ``batch_shape`` frames (counted as acted)."""
        uniform = torch.rand((*batch_shape, *self.low.shape), generator=self.generator).to(self.low.device)  # CPU's generator on every device
        self.frames_acted += max(1, math.prod(batch_shape))
        return self.low + (self.high - self.low) * uniform

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.warming_up:
            tensordict.set(self.action_key, self.draw(tuple(tensordict.batch_size)))
            return tensordict
        self.frames_acted += max(1, tensordict.batch_size.numel())
        return self.policy(tensordict)

    def get_extra_state(self) -> dict:
        return {"frames_acted": torch.tensor(self.frames_acted), "generator": self.generator.get_state()}

    def set_extra_state(self, state: dict) -> None:
        self.frames_acted = int(state["frames_acted"])
        self.generator.set_state(state["generator"])
