"""experiment=miniature: the paper's schedule (the schema's defaults, experiment=paper) scaled by one factor,
checked by composing both with Hydra for every recipe and task of the set."""
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from torchrl_esrl.run.config import validate_config

ROOT = Path(__file__).resolve().parents[1]


def composed(config: str, experiment: str, env: str):
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config, overrides=[f"experiment={experiment}", f"env={env}"])
    validate_config(cfg)
    return cfg


@pytest.mark.parametrize("env", ["halfcheetah", "walker2d", "swimmer", "ant"])
@pytest.mark.parametrize("config", ["config", "td3", "es"])
def test_miniature_scales_the_paper_by_one_factor(config, env):
    paper, mini = composed(config, "paper", env), composed(config, "miniature", env)
    m, paper_m = mini.td3.frames_per_iteration, paper.td3.frames_per_iteration
    factor = m / paper_m
    assert factor == pytest.approx(0.04) and mini.iterations == paper.iterations == 20
    # ES frames per iteration scale with g (whole episodes of the same population), so by the same factor
    assert mini.es.generations_per_iteration / paper.es.generations_per_iteration == pytest.approx(factor)
    assert mini.es.generations_per_iteration == m // 2000 and mini.buffer.min_size == m // 4  # g = M/2,000, K = M/4
    assert mini.buffer.min_size / paper.buffer.min_size == pytest.approx(factor)
    assert mini.td3.random_frames == (mini.buffer.min_size if config == "td3" else 0)  # Fujimoto's warm-up is K frames
    for key in ("es.population_size", "es.antithetic", "es.sigma", "es.lr", "buffer.capacity", "buffer.renormalize", "buffer.ratio",
                "td3.frames_per_batch", "td3.lr", "td3.updates_per_frame", "overwrite.window", "threshold.fraction", "env.max_episode_steps",
                "eval.episodes", "eval.final_episodes"):
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
