"""ERL (Khadka and Tumer, "Evolution-Guided Policy Gradient in Reinforcement Learning", NeurIPS 2018), the
"ERL" row of Table 1, as a Hydra recipe.

    python recipes/erl.py env=halfcheetah experiment=quick

A genetic algorithm (torchrl_esrl/es/ga.py: selection, elitism, crossover, mutation) beside a DDPG learner
(TorchRL's DDPGLoss; ``learner=td3|sac`` puts another in its place), one replay buffer shared by both. Each
generation (torchrl_esrl/algorithm/erl_iteration.py): every member plays ``ga.evaluations`` deterministic
episodes, its fitness their mean; the GA breeds; the learner plays one episode with its exploration noise; once
the buffer holds K (``buffer.min_size``) the learner takes one update per frame the generation played; every
``erl.sync_period`` generations its actor is copied over the member that scored lowest. Every episode goes to
the shared buffer. The returned policy is the GA champion: the best member of the last generation, as evaluated
(the policy whose score the authors report). The authors' values are the defaults (docs/deviations.md).

``buffer.mode=multi`` routes the population's episodes to good or bad by the threshold rule and the learner's
to noisy: ERL with the MultiBuffer, recipes/erl_buffers.py. Iteration i ends at the first generation's end
where the run has played (i + 1) x M frames, M = ``td3.frames_per_iteration``, so an experiment preset scales
it by its own factor; every frame, the population's and the learner's, counts.
"""
from __future__ import annotations

from omegaconf import DictConfig

from torchrl_esrl.algorithm.erl_iteration import COUNTERS, ERL_FRAMES, ERLConfig, ERLProgress, erl_iteration
from torchrl_esrl.collectors.es_collector import make_es_collector
from torchrl_esrl.collectors.td3_collector import TD3EnvState, make_frame_batches
from torchrl_esrl.data.multibuffer import buffer_holdings, make_multibuffer
from torchrl_esrl.data.threshold import make_threshold
from torchrl_esrl.envs import make_train_env
from torchrl_esrl.es.ga import GAConfig, ga_holdings, make_ga
from torchrl_esrl.modules.networks import cpu_actor, load_flat_parameters
from torchrl_esrl.objectives.learners import LearnerConfig, learner_holdings, make_learner
from torchrl_esrl.run.algorithm_info import AlgorithmInfo
from torchrl_esrl.run.lifecycle import Run, recipe_main

# One name per variant (buffer.mode, learner.name): runs of different variants are different rows.
ALGORITHMS = (
    AlgorithmInfo("erl", "ERL", returned="GA champion", rank=5, td3_frames=ERL_FRAMES),
    AlgorithmInfo("erl_td3", "ERL with TD3", returned="GA champion", rank=5, td3_frames=ERL_FRAMES),
    AlgorithmInfo("erl_sac", "ERL with SAC", returned="GA champion", rank=5, td3_frames=ERL_FRAMES),
    AlgorithmInfo("erl_buffers", "ERL (return-routed buffers)", returned="GA champion", rank=5, td3_frames=ERL_FRAMES),
    AlgorithmInfo("erl_buffers_td3", "ERL with TD3 (return-routed buffers)", returned="GA champion", rank=5,
                  td3_frames=ERL_FRAMES),
    AlgorithmInfo("erl_buffers_sac", "ERL with SAC (return-routed buffers)", returned="GA champion", rank=5,
                  td3_frames=ERL_FRAMES),
)
SECTIONS = {"ga": GAConfig, "erl": ERLConfig, "learner": LearnerConfig}
# With experiment=tiny (the tests' budget, tests/conftest.py): two generations an iteration, so that a stop
# after the first is a stop within an iteration, the learner injected from the second on, and one update in 20
# frames (15 a generation: stop points within the updates, in seconds).
TINY_OVERRIDES = ("ga.population_size=2", "erl.sync_period=1", "buffer.batch_size=64", "td3.updates_per_frame=0.05")


def train(cfg: DictConfig, run: Run) -> dict:
    env = make_train_env(cfg)
    learner = make_learner(cfg, env)  # DDPG; learner=td3|sac
    collector, frame_batches = make_frame_batches(cfg, env, learner)  # the learner's episodes, exploring
    ga = make_ga(cfg, learner.actor)  # members of the learner's actor's architecture, each initialised afresh
    population_collector = make_es_collector(cfg, learner.actor)  # the members' deterministic episodes
    buffer, threshold = make_multibuffer(cfg), make_threshold(cfg)  # one shared buffer, or good, bad and noisy
    at = run.progress.phase = ERLProgress()  # the iteration under way, checkpointed at every stop point
    champion = cpu_actor(learner.actor)
    load_flat_parameters(champion, ga.champion)  # the policy returned before any generation: the initial one
    run.start(champion, learner=learner, exploration=learner.exploration_policy, learner_env=TD3EnvState(collector),
              buffer=buffer, threshold=threshold, ga=ga, population_collector=population_collector)
    counters = run.progress.counters  # checkpointed with the run; erl_iteration advances them
    shared = cfg.buffer.mode == "shared"

    for iteration in run.iterations(algorithm(cfg).label):
        # Generations until the run has played (iteration + 1) x M frames, the population's and the learner's.
        budget = (iteration + 1) * cfg.td3.frames_per_iteration
        stats = erl_iteration(ga, learner, buffer, threshold, population_collector, frame_batches, counters, budget,
                              cfg.erl.sync_period, cfg.td3.updates_per_frame, shared, at, run.stop_point)
        run.log(
            iteration, counters["frames"], 0, eval_return=run.evaluate(ga.champion), generations=ga.generation,
            td3_updates=learner.updates, **{key: counters[key] for key in COUNTERS if key != "frames"}, **stats,
            **learner.metrics(), **threshold.metrics(), buffer_mode=cfg.buffer.mode,
            **{f"{name}_size": size for name, size in buffer.sizes().items()},
        )
    collector.shutdown()
    return run.finish(ga.champion, {
        "generations": ga.generation,
        "population_size": ga.population_size,
        "td3_updates": learner.updates,
        "injections": counters["injections"],
        "ratio": list(buffer.ratio),  # (0, 0, 1) in shared mode
        "buffer_mode": cfg.buffer.mode,
    })


def algorithm(cfg: DictConfig) -> AlgorithmInfo:
    """The variant ``cfg`` runs: the buffer mode, then the learner."""
    return ALGORITHMS[3 * (cfg.buffer.mode == "multi") + ("ddpg", "td3", "sac").index(cfg.learner.name)]


def holdings(cfg: DictConfig, sizes) -> list:
    """What :func:`train` builds: the learner, the shared buffer (three in multi mode), the GA and its generation."""
    buffers = 1 if cfg.buffer.mode == "shared" else 3
    return [*learner_holdings(cfg, sizes), *buffer_holdings(cfg, sizes, buffers=buffers), *ga_holdings(cfg, sizes)]


main = recipe_main(train, config_name="erl", algorithm=algorithm, holdings=holdings, sections=SECTIONS)

if __name__ == "__main__":
    main()
