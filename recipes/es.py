"""OpenAI-ES alone (Salimans et al. 2017), the ES half of ES-TD3Buffers without TD3 or buffers.

    python recipes/es.py env=halfcheetah experiment=quick

Same OpenES, population, sigma, Adam and ES collector as recipes/es_td3.py. One iteration =
``es.generations_per_iteration`` generations (ES-TD3Buffers' iteration), then a deterministic
evaluation of the mean, which is the returned policy.
"""
from __future__ import annotations

from omegaconf import DictConfig

from torchrl_esrl.algorithm.es_phase import GenerationReturns
from torchrl_esrl.collectors.es_collector import make_es_collector
from torchrl_esrl.envs import make_train_env
from torchrl_esrl.es.openes import es_holdings, make_es
from torchrl_esrl.modules.networks import make_actor_critic
from torchrl_esrl.run.algorithm_info import AlgorithmInfo
from torchrl_esrl.run.lifecycle import Run, recipe_main

ALGORITHMS = (AlgorithmInfo("es", "OpenAI-ES", returned="ES mean", rank=6),)


def train(cfg: DictConfig, run: Run) -> dict:
    actor, _ = make_actor_critic(cfg, make_train_env(cfg))  # the env only gives the actor its shapes
    es = make_es(cfg, actor)
    es_collector = make_es_collector(cfg, actor)
    run.start(actor, es=es, es_collector=es_collector)

    for iteration in run.iterations("ES"):
        returns = []
        for _ in range(cfg.es.generations_per_iteration):
            population = es.ask()
            generation = es_collector.evaluate(population, mirrored=es.mirrored(population))
            es.tell(population, generation.returns)
            returns.append(generation.returns)
        run.log(
            iteration,
            0,
            es_collector.frames,
            eval_return=run.evaluate(es.mean),
            es_generations=es.generation,
            **GenerationReturns(returns).metrics(),
        )
    return run.finish(es.mean, {"es_generations": es.generation})


def holdings(cfg: DictConfig, sizes) -> list:
    """What :func:`train` builds: OpenAI-ES and its generation; no replay buffer, no critic."""
    return es_holdings(cfg, sizes)


main = recipe_main(train, config_name="es", algorithm=ALGORITHMS[0], holdings=holdings)

if __name__ == "__main__":
    main()
