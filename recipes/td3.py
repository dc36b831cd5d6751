"""TD3 alone (Fujimoto et al. 2018), the RL baseline of ES-TD3Buffers, in the same harness.

    python recipes/td3.py env=walker2d experiment=quick
    python recipes/td3.py env=walker2d experiment=quick learner=sac   # SAC (or DDPG) alone

The same actor, critics, learner and exploration as the TD3 half of recipes/es_td3.py, with
one replay buffer (``MultiBuffer(ratio=(0, 0, 1))``, i.e. only the noisy buffer) and no ES.
One iteration = ``td3.frames_per_iteration`` frames, then a deterministic evaluation of the actor.
"""
from __future__ import annotations

from omegaconf import DictConfig

from torchrl_esrl.algorithm.td3_phase import td3_phase
from torchrl_esrl.collectors.td3_collector import TD3EnvState, make_frame_batches
from torchrl_esrl.data.multibuffer import buffer_holdings, make_multibuffer
from torchrl_esrl.envs import make_train_env
from torchrl_esrl.modules.networks import flat_parameters
from torchrl_esrl.objectives.learners import LEARNERS, LearnerConfig, learner_holdings, make_learner
from torchrl_esrl.run.algorithm_info import AlgorithmInfo
from torchrl_esrl.run.lifecycle import Run, recipe_main

ALGORITHMS = (  # one per learner, in LEARNERS' order
    AlgorithmInfo("td3", "TD3", returned="TD3 actor", rank=4),
    AlgorithmInfo("ddpg", "DDPG", returned="DDPG actor", rank=14),
    AlgorithmInfo("sac", "SAC", returned="SAC actor (mean action)", rank=24),
)


def train(cfg: DictConfig, run: Run) -> dict:
    env = make_train_env(cfg)
    learner = make_learner(cfg, env)  # TD3, or learner=ddpg|sac in its place
    actor = learner.actor  # the deterministic policy it evaluates and returns (SAC: the mean action)
    collector, frame_batches = make_frame_batches(cfg, env, learner)
    # One buffer: the MultiBuffer with all of the batch from "noisy" is a plain TD3 replay buffer.
    buffer = make_multibuffer(cfg, one_buffer=True)
    run.start(actor, td3=learner, exploration=learner.exploration_policy, td3_env=TD3EnvState(collector), buffer=buffer)
    episodes = run.progress.counters.setdefault("td3_train_episodes", 0)

    for iteration in run.iterations(algorithm(cfg).label):
        stats = td3_phase(
            cfg.td3.frames_per_iteration, frame_batches, learner, buffer,
            updates_per_frame=cfg.td3.updates_per_frame, on_batch=run.on_td3_batch, progress=run.progress.td3_phase,
        )
        episodes = run.progress.counters["td3_train_episodes"] = episodes + stats["episodes"]
        run.log(
            iteration,
            run.progress.frames_now,
            0,
            eval_return=run.evaluate(flat_parameters(actor)),
            td3_updates=learner.updates,
            td3_train_episodes=episodes,
            critic_loss=stats["critic_loss"],
            actor_loss=stats["actor_loss"],
            **learner.metrics(),  # the learner's own (SAC: its entropy temperature)
        )
    collector.shutdown()
    return run.finish(flat_parameters(actor), {"td3_updates": learner.updates})


def algorithm(cfg: DictConfig) -> AlgorithmInfo:
    """The learner ``cfg`` runs."""
    return ALGORITHMS[list(LEARNERS).index(cfg.learner.name)]


def holdings(cfg: DictConfig, sizes) -> list:
    """What :func:`train` builds: the learner and one replay buffer."""
    return [*learner_holdings(cfg, sizes), *buffer_holdings(cfg, sizes, buffers=1)]


main = recipe_main(
    train, config_name="td3", algorithm=algorithm, holdings=holdings, sections={"learner": LearnerConfig},
)

if __name__ == "__main__":
    main()
