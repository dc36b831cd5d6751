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

from omegaconf import DictConfig

from torchrl_esrl.algorithm.cem_rl_iteration import (
    POPULATION_FRAMES, GenerationsProgress, cem_rl_iteration, cem_rl_metrics, population_under_way_holdings,
)
from torchrl_esrl.collectors.es_collector import make_es_collector
from torchrl_esrl.data.multibuffer import buffer_holdings, make_multibuffer
from torchrl_esrl.envs import make_train_env
from torchrl_esrl.es.cem import CEMConfig, cem_holdings, make_cem
from torchrl_esrl.modules.networks import make_actor_critic
from torchrl_esrl.objectives.td3 import make_td3, td3_holdings
from torchrl_esrl.run.algorithm_info import AlgorithmInfo
from torchrl_esrl.run.lifecycle import Run, recipe_main

ALGORITHMS = (AlgorithmInfo("cem_rl", "CEM-RL", returned="CEM mean", rank=5, td3_frames=POPULATION_FRAMES),)
# With experiment=tiny (the tests' budget, tests/conftest.py): a population of 4 that learns from its first generation.
TINY_OVERRIDES = ("cem.population_size=4", "cem.start_frames=0")


def train(cfg: DictConfig, run: Run) -> dict:
    env = make_train_env(cfg)
    actor, critic = make_actor_critic(cfg, env)
    td3 = make_td3(cfg, actor, critic, env.action_spec)
    buffer = make_multibuffer(cfg, one_buffer=True)
    cem = make_cem(cfg, actor)
    population_collector = make_es_collector(cfg, actor)  # one deterministic episode per member
    rl_members = int(cfg.cem.population_size * cfg.cem.rl_fraction)
    generations = run.progress.phase = GenerationsProgress()  # the iteration under way, checkpointed at stop points
    run.start(actor, td3=td3, buffer=buffer, cem=cem, population_collector=population_collector)
    counters = run.progress.counters  # checkpointed with the run; cem_rl_iteration advances them
    for iteration in run.iterations("CEM-RL"):
        # Generations until M new frames: the RL half trained, every member's episode into the buffer,
        # the elites update CEM.
        stats = cem_rl_iteration(
            cem, td3, buffer, population_collector, counters, cfg.td3.frames_per_iteration, cfg.cem.start_frames,
            rl_members, cfg.td3.tau, at=generations, stop_point=run.stop_point,
        )
        mean_return = run.evaluate(cem.mean)
        run.log(iteration, counters["frames"], 0, eval_return=mean_return, **cem_rl_metrics(cem, td3, counters, stats))
    return run.finish(cem.mean, {
        "generations": cem.generation, "td3_updates": td3.updates, "population_size": int(cfg.cem.population_size),
    })


def holdings(cfg: DictConfig, sizes) -> list:
    """What :func:`train` builds: the TD3 learner, one replay buffer, the CEM and its generation (and
    the population a stop within its gradient steps writes)."""
    return [*td3_holdings(cfg, sizes), *buffer_holdings(cfg, sizes, buffers=1), *cem_holdings(cfg, sizes),
            *population_under_way_holdings(cfg, sizes)]


main = recipe_main(train, config_name="cem_rl", algorithm=ALGORITHMS[0], holdings=holdings, sections={"cem": CEMConfig})

if __name__ == "__main__":
    main()
