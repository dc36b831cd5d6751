"""CEM-RL (Pourchot and Sigaud, ICLR 2019) with ES-TD3Buffers' return-routed MultiBuffer.

    python recipes/cem_rl_buffers.py env=halfcheetah experiment=quick

recipes/cem_rl.py with its one replay buffer replaced by the good, bad and noisy buffers of
ES-TD3Buffers (Section 3.1): each generation, the episodes of the CEM members go to *good* when
their return reaches the threshold (``data/threshold.py``, ``0.9 x best``), else to *bad*; the
episodes of the RL members (the first ``cem.rl_fraction`` of the population, the members the
critic trains) go to *noisy*, as TD3's own transitions do in ES-TD3Buffers, and their returns
raise the best return. The critic and the RL members train on batches drawn at ``buffer.ratio``
once every buffer holds ``buffer.min_size`` (K). Everything else is recipes/cem_rl.py.
``buffer.mode=shared`` puts every episode in one buffer, which is CEM-RL itself.
Where the routing is this project's choice, docs/deviations.md says so.
"""
from __future__ import annotations

from omegaconf import DictConfig

from torchrl_esrl.algorithm.cem_rl_iteration import (
    POPULATION_FRAMES,
    GenerationsProgress,
    cem_rl_iteration,
    cem_rl_metrics,
    one_buffer,
    population_under_way_holdings,
    routed_by_return,
)
from torchrl_esrl.collectors.es_collector import make_es_collector
from torchrl_esrl.data.multibuffer import buffer_holdings, make_multibuffer
from torchrl_esrl.data.threshold import make_threshold
from torchrl_esrl.envs import make_train_env
from torchrl_esrl.es.cem import CEMConfig, cem_holdings, make_cem
from torchrl_esrl.modules.networks import make_actor_critic
from torchrl_esrl.objectives.td3 import make_td3, td3_holdings
from torchrl_esrl.run.algorithm_info import AlgorithmInfo
from torchrl_esrl.run.lifecycle import Run, recipe_main

ALGORITHMS = (
    AlgorithmInfo("cem_rl_buffers", "CEM-RL (return-routed buffers)", returned="CEM mean", rank=5,
                  td3_frames=POPULATION_FRAMES),
    AlgorithmInfo("cem_rl_buffers_shared", "CEM-RL (return-routed buffers, one shared buffer)", returned="CEM mean",
                  rank=5, td3_frames=POPULATION_FRAMES),
)
# With experiment=tiny (the tests' budget, tests/conftest.py): a good episode by the first generation's end,
# so that the strict readiness rule lets the RL members learn in the second.
TINY_OVERRIDES = (
    "cem.population_size=6", "cem.start_frames=0",
    "buffer.batch_size=32", "buffer.min_size=32", "buffer.renormalize=false",
)


def train(cfg: DictConfig, run: Run) -> dict:
    env = make_train_env(cfg)
    actor, critic = make_actor_critic(cfg, env)
    td3 = make_td3(cfg, actor, critic, env.action_spec)
    buffer, threshold = make_multibuffer(cfg), make_threshold(cfg)  # good, bad, noisy at buffer.ratio
    cem = make_cem(cfg, actor)
    population_collector = make_es_collector(cfg, actor)  # one deterministic episode per member
    rl_members = int(cfg.cem.population_size * cfg.cem.rl_fraction)
    route = one_buffer if cfg.buffer.mode == "shared" else routed_by_return(threshold, rl_members)
    generations = run.progress.phase = GenerationsProgress()  # the iteration under way, checkpointed at stop points
    run.start(actor, td3=td3, buffer=buffer, threshold=threshold, cem=cem, population_collector=population_collector)
    counters = run.progress.counters  # checkpointed with the run; cem_rl_iteration advances them
    for iteration in run.iterations("CEM-RL (return-routed buffers)"):
        # Generations until M new frames: the RL half trained on batches at the ratio once every buffer
        # holds K; RL members' episodes to noisy, CEM members' to good or bad by the threshold; the elites update CEM.
        stats = cem_rl_iteration(
            cem, td3, buffer, population_collector, counters, cfg.td3.frames_per_iteration, cfg.cem.start_frames,
            rl_members, cfg.td3.tau, route, at=generations, stop_point=run.stop_point,
        )
        run.log(
            iteration, counters["frames"], 0, eval_return=run.evaluate(cem.mean),
            **cem_rl_metrics(cem, td3, counters, stats), **threshold.metrics(),
            **{f"{name}_size": size for name, size in buffer.sizes().items()},
        )
    return run.finish(cem.mean, {
        "generations": cem.generation,
        "td3_updates": td3.updates,
        "population_size": int(cfg.cem.population_size),
        "ratio": list(buffer.ratio),  # (0, 0, 1) in shared mode
        "buffer_mode": cfg.buffer.mode,
    })


def algorithm(cfg: DictConfig) -> AlgorithmInfo:
    """The variant ``cfg`` runs: routed buffers, or one shared buffer."""
    return ALGORITHMS[cfg.buffer.mode == "shared"]


def holdings(cfg: DictConfig, sizes) -> list:
    """What :func:`train` builds: the TD3 learner, the three buffers (one in shared mode), the CEM and its
    generation (and the population a stop within its gradient steps writes)."""
    return [*td3_holdings(cfg, sizes), *buffer_holdings(cfg, sizes, buffers=1 if cfg.buffer.mode == "shared" else 3),
            *cem_holdings(cfg, sizes), *population_under_way_holdings(cfg, sizes)]


main = recipe_main(
    train, config_name="cem_rl_buffers", algorithm=algorithm, holdings=holdings, sections={"cem": CEMConfig},
)

if __name__ == "__main__":
    main()
