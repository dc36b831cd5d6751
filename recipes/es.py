"""OpenAI-ES alone (Salimans et al. 2017), the ES half of ES-TD3Buffers without TD3 or buffers.

    python recipes/es.py env=halfcheetah experiment=quick

Same OpenES, population, sigma, Adam and ES collector as recipes/es_td3.py. One iteration =
``es.generations_per_iteration`` generations (ES-TD3Buffers' iteration), then a deterministic
evaluation of the mean, which is the returned policy.
"""
from __future__ import annotations

from omegaconf import DictConfig

from torchrl_esrl.algorithm.es_phase import GenerationReturns
from torchrl_esrl.run.factories import make_actor_critic, make_es, make_es_collector, make_train_env
from torchrl_esrl.run.algorithm_info import AlgorithmInfo
from torchrl_esrl.run.lifecycle import Run, recipe_main

ALGORITHMS = (AlgorithmInfo("es", "OpenAI-ES", "ES mean", rank=6),)


def train(cfg: DictConfig, run: Run) -> dict:
    actor, _ = make_actor_critic(cfg, make_train_env(cfg))  # the env only gives the actor its shapes
    es = make_es(cfg, actor)
    es_collector = make_es_collector(cfg, actor)
    run.start(actor, es=es, es_collector=es_collector)

    for iteration in run.iterations("ES"):
        returns = []
        for _ in range(cfg.es.generations_per_iteration):
            generation = es_collector.evaluate(es.ask(), mirrored=es.mirrored())
            es.tell(generation.returns)
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


main = recipe_main(train, config_name="es", algorithm="es")

if __name__ == "__main__":
    main()
