"""The cross-entropy method alone (CEM), the "CEM" row of Table 1: the sepCEM of CEM-RL's authors
(Pourchot and Sigaud, ICLR 2019; apourchot/CEM-RL ``ES.py``) without RL, in the same harness.

    python recipes/cem.py env=halfcheetah experiment=quick

Each generation: sample a population from the diagonal Gaussian (antithetic pairs), every member
plays one deterministic episode (its return is its fitness), and the top half update the mean and
the variance (torchrl_esrl/es/cem.py). The returned policy is the CEM mean.

Same DiagonalCEM, population evaluation and ``cem`` section as recipes/cem_rl.py, which with
``cem.rl_fraction=0`` runs the same generations. Iteration i ends at the first generation's end
where the run has played (i + 1) x M frames, M = ``td3.frames_per_iteration``: the frames the TD3
rows have at iteration i, so an experiment preset scales it by the preset's own factor
(docs/deviations.md, 44). Its frames are ES frames (no TD3).
"""
from __future__ import annotations

from omegaconf import DictConfig

from torchrl_esrl.algorithm.cem_rl_iteration import GenerationsProgress
from torchrl_esrl.collectors.es_collector import make_es_collector
from torchrl_esrl.collectors.generation import population_returns
from torchrl_esrl.envs import make_train_env
from torchrl_esrl.es.cem import CEMConfig, cem_holdings, make_cem
from torchrl_esrl.modules.networks import make_actor_critic
from torchrl_esrl.run.algorithm_info import AlgorithmInfo
from torchrl_esrl.run.lifecycle import Run, recipe_main

ALGORITHMS = (AlgorithmInfo("cem", "CEM", returned="CEM mean", rank=5),)
# With experiment=tiny (the tests' budget, tests/conftest.py): two generations an iteration, so that a
# stop after the first is a stop within an iteration.
TINY_OVERRIDES = ("cem.population_size=2",)


def train(cfg: DictConfig, run: Run) -> dict:
    actor, _ = make_actor_critic(cfg, make_train_env(cfg))  # the env only gives the actor its shapes
    cem = make_cem(cfg, actor)
    population_collector = make_es_collector(cfg, actor)  # one deterministic episode per member
    generations = run.progress.phase = GenerationsProgress()  # the iteration under way, checkpointed at stop points
    run.start(actor, cem=cem, population_collector=population_collector)

    for iteration in run.iterations("CEM"):
        # Whole generations until the run has played (iteration + 1) x M frames (none where the last overshot it).
        while population_collector.frames < (iteration + 1) * cfg.td3.frames_per_iteration:
            population = cem.ask()
            generation = population_collector.evaluate(population)
            cem.tell(population, generation.returns)  # the elites update the mean and the variance
            generations.finish_generation(generation.frames, generation.returns)
            run.stop_point(f"after CEM generation {cem.generation}")
        returns = generations.finish_iteration()["returns"]
        run.log(
            iteration,
            0,
            population_collector.frames,
            eval_return=run.evaluate(cem.mean),
            generations=cem.generation,
            cem_mean_std=cem.var.sqrt().mean().item(),
            **population_returns(returns),
        )
    return run.finish(cem.mean, {"generations": cem.generation, "population_size": int(cfg.cem.population_size)})


def holdings(cfg: DictConfig, sizes) -> list:
    """What :func:`train` builds: the CEM and its generation; no replay buffer, no critic."""
    return cem_holdings(cfg, sizes)


main = recipe_main(train, config_name="cem", algorithm=ALGORITHMS[0], holdings=holdings, sections={"cem": CEMConfig})

if __name__ == "__main__":
    main()
