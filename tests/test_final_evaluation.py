"""The final evaluation has a seed stream of its own (docs/deviations.md 29): its episodes do not
depend on how many per-iteration evaluations ran before it, and never repeat theirs."""
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir

from torchrl_esrl.modules.networks import flat_parameters
from torchrl_esrl.envs import make_train_env
from torchrl_esrl.modules.networks import make_actor_critic
from torchrl_esrl.run.harness import RunHarness, final_episode_seeds

ROOT = Path(__file__).resolve().parents[1]
OVERRIDES = ["env=swimmer", "env.max_episode_steps=30", "eval.episodes=3", "eval.final_episodes=4", "logger.backend=", "logger.progress=false"]


def make_harness(run_dir):
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=OVERRIDES)
    harness = RunHarness(cfg, run_dir, algorithm="td3")
    actor, _ = make_actor_critic(cfg, make_train_env(cfg))
    harness.attach_actor(actor)
    return harness, flat_parameters(actor)


def test_final_return_does_not_depend_on_earlier_evaluations(tmp_path):
    harness, vector = make_harness(tmp_path / "a")
    first = harness.evaluate_final(vector)
    harness, vector = make_harness(tmp_path / "b")
    iteration_returns = [harness.evaluate(vector) for _ in range(3)]  # three iterations' evaluations first
    assert harness.evaluate_final(vector) == first
    assert len(set(iteration_returns)) > 1  # the per-iteration stream moves on; the final one stays put


def test_final_seeds_are_apart_from_the_per_iteration_stream():
    final = final_episode_seeds(0, 10)
    assert final == final_episode_seeds(0, 10) and final != final_episode_seeds(1, 10)
    per_iteration = np.random.default_rng(0 + 1000).integers(0, 2**31 - 1, size=10_000)  # the evaluator's stream (seed + 1000)
    assert not set(final) & set(per_iteration.tolist())
