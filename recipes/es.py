"""OpenAI-ES alone (Salimans et al. 2017), the ES half of ES-TD3Buffers without TD3 or buffers.

    python recipes/es.py env=halfcheetah experiment=quick

Same OpenES, population, sigma, Adam and ES collector as recipes/es_td3.py. One iteration =
``es.generations_per_iteration`` generations (ES-TD3Buffers' checkpoint), then a deterministic
evaluation of the mean, which is the returned policy.
"""
from __future__ import annotations

import sys
from pathlib import Path

import torch
from omegaconf import DictConfig

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing

from torchrl_esrl.run.factories import make_actor_critic, make_es, make_es_collector, make_train_env  # noqa: E402
from torchrl_esrl.run.harness import RunHarness, hydra_main  # noqa: E402


def train(cfg: DictConfig, run_dir: Path) -> dict:
    harness = RunHarness(cfg, run_dir, algorithm="es", columns=("es_generations", "es_generation_mean_return", "es_generation_max_return"))
    actor, _ = make_actor_critic(cfg, make_train_env(cfg))  # the env only gives the actor its shapes
    es = make_es(cfg, actor)
    es_collector = make_es_collector(cfg, actor)
    harness.attach_actor(actor)

    for iteration in harness.iterations(desc="ES"):
        returns = []
        for _ in range(cfg.es.generations_per_iteration):
            generation = es_collector.evaluate(es.ask())
            es.tell(generation.returns)
            returns.append(generation.returns)
        returns = torch.cat(returns) if returns else torch.zeros(1)
        harness.log(
            iteration,
            0,
            es_collector.frames,
            eval_return=harness.evaluate(es.mean),
            es_generations=es.generation,
            es_generation_mean_return=returns.mean().item(),
            es_generation_max_return=returns.max().item(),
        )
    return harness.finish(es.mean, {"es_generations": es.generation})


main = hydra_main(train, config_name="es")

if __name__ == "__main__":
    main()
