"""TD3 alone (Fujimoto et al. 2018), the RL baseline of ES-TD3Buffers, in the same harness.

    python recipes/td3.py env=walker2d experiment=quick

The same actor, critics, TD3 learner and exploration as the TD3 half of recipes/es_td3.py, with
one replay buffer (``MultiBuffer(ratio=(0, 0, 1))``, i.e. only the noisy buffer) and no ES.
One iteration = ``td3.frames_per_iteration`` frames, then a deterministic evaluation of the actor.
"""
from __future__ import annotations

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing

from torchrl_esrl.data.multibuffer import MultiBuffer  # noqa: E402
from torchrl_esrl.run.factories import make_actor_critic, make_td3, make_td3_batches, make_train_env  # noqa: E402
from torchrl_esrl.run.harness import RunHarness, hydra_main  # noqa: E402
from torchrl_esrl.modules.networks import flat_parameters  # noqa: E402
from torchrl_esrl.algorithm.td3_phase import td3_phase  # noqa: E402


def train(cfg: DictConfig, run_dir: Path) -> dict:
    harness = RunHarness(cfg, run_dir, algorithm="td3", columns=("td3_updates", "td3_train_episodes", "critic_loss", "actor_loss"))
    env = make_train_env(cfg)
    actor, critic = make_actor_critic(cfg, env)
    td3 = make_td3(cfg, actor, critic, env.action_spec)
    collector, td3_batches = make_td3_batches(cfg, env, td3)
    # One buffer: the MultiBuffer with all of the batch from "noisy" is a plain TD3 replay buffer.
    buffer = MultiBuffer(ratio=(0, 0, 1), capacity=cfg.buffer.capacity, batch_size=cfg.buffer.batch_size, min_size=cfg.buffer.min_size, device=cfg.device)
    harness.attach_actor(actor)

    td3_frames, episodes = 0, 0
    for iteration in harness.iterations(desc="TD3"):
        stats = td3_phase(cfg.td3.frames_per_iteration, td3_batches, td3, buffer, updates_per_frame=cfg.td3.updates_per_frame)
        td3_frames += stats["frames"]
        episodes += stats["episodes"]
        harness.log(
            iteration,
            td3_frames,
            0,
            eval_return=harness.evaluate(flat_parameters(actor)),
            td3_updates=td3.updates,
            td3_train_episodes=episodes,
            critic_loss=stats.get("critic_loss", ""),
            actor_loss=stats.get("actor_loss", ""),
        )
    collector.shutdown()
    return harness.finish(flat_parameters(actor), {"td3_updates": td3.updates})


main = hydra_main(train, config_name="td3")

if __name__ == "__main__":
    main()
