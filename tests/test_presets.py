"""experiment=miniature and experiment=quarter: the paper's schedule (the schema's defaults, experiment=paper)
scaled by one factor, checked by composing both with Hydra for every recipe (tests/conftest.py's
``RECIPES``) and task of the sets."""
from pathlib import Path

import pytest
from conftest import RECIPES, own_keys, recipe_of
from hydra import compose, initialize_config_dir

from torchrl_esrl.run.config import validate_config

ROOT = Path(__file__).resolve().parents[1]


def composed(config: str, experiment: str, env: str):
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config, overrides=[f"experiment={experiment}", f"env={env}"])
    validate_config(cfg)
    return cfg


# preset -> (its share of the paper's TD3 frames, its g: M / 2,000 rounded half up)
SCALED = {"miniature": (0.04, 2), "quarter": (0.25, 13)}


@pytest.mark.parametrize("env", ["halfcheetah", "walker2d", "swimmer", "ant"])
@pytest.mark.parametrize("script", sorted(RECIPES))
@pytest.mark.parametrize("preset", sorted(SCALED))
def test_scaled_presets_scale_the_paper_by_one_factor(preset, script, env):
    config = recipe_of(script).config_name
    paper, mini = composed(config, "paper", env), composed(config, preset, env)
    share, generations = SCALED[preset]
    m, paper_m = mini.td3.frames_per_iteration, paper.td3.frames_per_iteration
    factor = m / paper_m
    assert factor == pytest.approx(share) and mini.iterations == paper.iterations == 20
    assert mini.experiment_name == preset
    # ES frames per iteration scale with g (whole episodes of the same population): g = M / 2,000, rounded half up
    assert mini.es.generations_per_iteration == generations == int(m / 2000 + 0.5)
    assert mini.es.generations_per_iteration / paper.es.generations_per_iteration == pytest.approx(factor, rel=0.05)  # 13 for 12.5: +4%
    assert mini.buffer.min_size == m // 4  # K = M/4
    assert mini.buffer.min_size / paper.buffer.min_size == pytest.approx(factor)
    assert mini.td3.random_frames * paper_m == paper.td3.random_frames * m  # TD3 alone's warm-up is K frames, so it scales; 0 elsewhere
    for key in ("es.population_size", "es.antithetic", "es.sigma", "es.lr", "buffer.capacity", "buffer.renormalize", "buffer.ratio",
                "td3.frames_per_batch", "td3.lr", "td3.updates_per_frame", "overwrite.window", "threshold.fraction", "env.max_episode_steps",
                "eval.episodes", "eval.final_episodes", *(key for key, _ in own_keys(script))):
        first, second = (cfg for cfg in (paper, mini))
        for part in key.split("."):
            first, second = first[part], second[part]
        assert first == second, key  # not scaled: the paper's value


@pytest.mark.parametrize("env", ["halfcheetah", "walker2d"])
def test_the_iteration_benchmark_times_the_paper_config(env):
    """benchmarks.iteration extrapolates the paper run: it must compose the recipe's own paper config."""
    from benchmarks.iteration import paper_config

    expected = composed("config", "paper", env)
    expected.logger.progress = False  # a benchmark prints no bar
    assert paper_config(env) == expected
