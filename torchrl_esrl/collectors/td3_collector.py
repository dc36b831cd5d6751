"""The TD3 side's collector (paper, Algorithm 1 "act with exploration noise"): a TorchRL
``Collector`` over the training env, acting with the exploration policy."""
from __future__ import annotations

from tensordict import TensorDictBase
from torchrl.collectors import Collector


def make_td3_collector(env, td3, frames_per_batch: int = 1) -> Collector:
    """TorchRL collector acting with the exploration policy; runs for as long as it is iterated."""
    return Collector(
        env,
        td3.exploration_policy,
        frames_per_batch=int(frames_per_batch),
        total_frames=-1,
        auto_register_policy_transforms=False,
    )


def finished_episode_returns(batch: TensorDictBase) -> list[float]:
    """Returns of the episodes that ended inside a collected batch (from TorchRL's ``RewardSum``)."""
    done = batch.get(("next", "done")).reshape(-1)
    if not done.any():
        return []
    return batch.get(("next", "episode_reward")).reshape(-1)[done].tolist()
