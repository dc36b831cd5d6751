"""CEM-RL (Pourchot and Sigaud, ICLR 2019) in the harness of ES-TD3Buffers.

    python recipes/cem_rl.py env=halfcheetah experiment=quick

Each generation, as the authors' code (``es_grad.py``) schedules it: sample a population from
the diagonal CEM; once ``cem.start_frames`` frames were played and the buffer is ready, each of
the first half of the population is loaded into the TD3 actor with a fresh Adam and gets F/half
critic steps then F actor steps (F = frames of the previous generation,
torchrl_esrl/es/cem.py:cem_rl_gradient_steps); every member then plays one deterministic
episode into the one replay buffer, and the top half update the CEM mean and variance. The
returned policy is the CEM mean.

Every frame is both a fitness evaluation and a TD3 training frame: all frames are counted as
``td3_frames`` (``es_frames`` stays 0). One iteration = generations until
``td3.frames_per_iteration`` new frames.
"""
from __future__ import annotations

import torch
from omegaconf import DictConfig

from torchrl_esrl.es.cem import cem_rl_gradient_steps
from torchrl_esrl.run.factories import make_actor_critic, make_cem, make_multibuffer, make_es_collector, make_td3, make_train_env
from torchrl_esrl.run.algorithm_info import AlgorithmInfo
from torchrl_esrl.run.lifecycle import Run, recipe_main

ALGORITHMS = (AlgorithmInfo("cem_rl", "CEM-RL", "CEM mean", rank=5),)


def train(cfg: DictConfig, run: Run) -> dict:
    env = make_train_env(cfg)
    actor, critic = make_actor_critic(cfg, env)
    td3 = make_td3(cfg, actor, critic, env.action_spec)
    buffer = make_multibuffer(cfg, one_buffer=True)
    cem = make_cem(cfg, actor)
    rl_members = int(cfg.cem.population_size * cfg.cem.rl_fraction)
    population_collector = make_es_collector(cfg, actor)  # one deterministic episode per member
    run.start(actor, td3=td3, buffer=buffer, cem=cem, population_collector=population_collector)
    counters = run.progress.counters  # checkpointed with the run
    frames, last_generation_frames = counters.setdefault("frames", 0), counters.setdefault("last_generation_frames", 0)
    actor_steps = counters.setdefault("actor_steps", 0)
    for iteration in run.iterations("CEM-RL"):
        iteration_frames, returns, critic_losses = 0, [], []
        while iteration_frames < cfg.td3.frames_per_iteration:
            population = cem.ask()
            # RL half: per member, F/half critic steps then F actor steps (F = last generation's frames).
            if frames + iteration_frames > cfg.cem.start_frames and buffer.ready() and rl_members > 0:
                steps = cem_rl_gradient_steps(td3, buffer, population, rl_members, last_generation_frames, cfg.td3.tau)
                critic_losses += steps["critic_losses"]
                actor_steps += steps["actor_steps"]
            generation = population_collector.evaluate(population)
            buffer.extend(generation.transitions, "noisy")
            cem.tell(population, generation.returns)
            last_generation_frames = generation.frames
            iteration_frames += generation.frames
            returns.append(generation.returns)
        frames += iteration_frames
        counters.update(frames=frames, last_generation_frames=last_generation_frames, actor_steps=actor_steps)
        returns = torch.cat(returns)
        run.log(
            iteration,
            frames,
            0,
            eval_return=run.evaluate(cem.mean),
            generations=cem.generation,
            td3_updates=td3.updates,
            actor_steps=actor_steps,
            population_mean_return=returns.mean().item(),
            population_max_return=returns.max().item(),
            critic_loss=sum(critic_losses) / len(critic_losses) if critic_losses else "",
            cem_mean_std=cem.var.sqrt().mean().item(),
        )
    return run.finish(cem.mean, {"generations": cem.generation, "td3_updates": td3.updates, "population_size": int(cfg.cem.population_size)})


main = recipe_main(train, config_name="cem_rl", algorithm="cem_rl")

if __name__ == "__main__":
    main()
