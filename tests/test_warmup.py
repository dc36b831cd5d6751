"""Fujimoto's uniform-random warm-up (td3.random_frames) as a policy module, through a real
TorchRL collector, and its exact resumption from a checkpoint."""
import pytest
import torch
from torchrl.checkpoint import Checkpoint

from omegaconf import OmegaConf

from torchrl_esrl.envs import make_env
from torchrl_esrl.modules.networks import make_actor, make_critic
from torchrl_esrl.modules.warmup import RandomWarmup
from torchrl_esrl.objectives.td3 import TD3
from torchrl_esrl.collectors.td3_collector import make_frame_batches


def make_td3_with_warmup(frames: int, seed: int = 7):
    torch.manual_seed(0)
    env = make_env("swimmer", seed=0, max_episode_steps=30)
    actor = make_actor(8, env.action_spec, (16, 16))
    td3 = TD3(actor, make_critic(8, 2, (16, 16)), env.action_spec)
    td3.exploration_policy = RandomWarmup(td3.exploration_policy, env.action_spec, frames, seed=seed)
    return env, td3


def collect_actions(env, td3, batches: int, restore_from=None, fast: bool = True) -> torch.Tensor:
    config = OmegaConf.create({"device": "cpu", "implementation": "fast" if fast else "reference", "td3": {"frames_per_batch": 10}})
    collector, frame_batches = make_frame_batches(config, env, td3)  # the recipes' factory
    assert type(collector).__name__ == ("GymTD3Collector" if fast else "Collector")
    if restore_from is not None:  # as the recipes do: components built, then the checkpoint loaded
        Checkpoint(exploration=td3.exploration_policy).load(restore_from)
    actions = [next(frame_batches)["action"].reshape(-1, 2) for _ in range(batches)]
    collector.shutdown()
    return torch.cat(actions)


@pytest.mark.parametrize("fast", [False, True], ids=["torchrl_collector", "gym_td3_collector"])
def test_first_frames_are_uniform_from_the_seeded_generator_then_the_noisy_actor(fast):
    env, td3 = make_td3_with_warmup(frames=30)
    actions = collect_actions(env, td3, batches=5, fast=fast)
    generator = torch.Generator().manual_seed(7)
    low, high = env.action_spec.space.low, env.action_spec.space.high
    expected = torch.stack([low + (high - low) * torch.rand(2, generator=generator) for _ in range(30)])
    torch.testing.assert_close(actions[:30], expected)
    assert td3.exploration_policy.frames_acted == 50 and not td3.exploration_policy.warming_up
    # after the warm-up the generator is no longer drawn from: actions are the actor's plus noise
    assert not torch.allclose(actions[30:40], torch.stack([low + (high - low) * torch.rand(2, generator=generator) for _ in range(10)]))


@pytest.mark.parametrize("fast", [False, True], ids=["torchrl_collector", "gym_td3_collector"])
def test_warmup_resumes_exactly_from_a_checkpoint(tmp_path, fast):
    env, td3 = make_td3_with_warmup(frames=40)
    whole = collect_actions(env, td3, batches=4, fast=fast)

    env, td3 = make_td3_with_warmup(frames=40)
    first = collect_actions(env, td3, batches=2, fast=fast)
    Checkpoint(exploration=td3.exploration_policy).save(tmp_path / "ckpt")
    env, td3 = make_td3_with_warmup(frames=40, seed=123)  # a different generator, overwritten by the load
    second = collect_actions(env, td3, batches=2, restore_from=tmp_path / "ckpt", fast=fast)
    assert td3.exploration_policy.frames_acted == 40
    torch.testing.assert_close(torch.cat([first, second]), whole)


def test_fast_collector_acts_as_the_torchrl_collector_through_and_after_the_warmup():
    """The direct stepping path honours the warm-up exactly as TorchRL's Collector does."""
    runs = []
    for fast in (False, True):
        env, td3 = make_td3_with_warmup(frames=30)
        torch.manual_seed(1)  # the exploration noise after the warm-up draws from torch's global stream
        runs.append(collect_actions(env, td3, batches=5, fast=fast))
    torch.testing.assert_close(runs[1], runs[0])
