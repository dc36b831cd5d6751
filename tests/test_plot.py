"""A run's learning curve (torchrl_esrl/run/plot.py) draws whatever evaluation columns the run
logs: every learner's it logs, and the returned policy's unless a learner's curve is it."""
import pytest

from torchrl_esrl.run.algorithm_info import AlgorithmInfo
from torchrl_esrl.run.metrics import MetricsLog, read_metrics
from torchrl_esrl.run.plot import draw_es_vs_td3, plot_run, pyplot

SUMMARY = {"env": "HalfCheetah-v5", "seed": 0, "algorithm": "a", "initial_return": -1.0}


@pytest.mark.parametrize(
    "learners, returned, drawn",
    [
        ({}, "TD3 actor", ["TD3 actor"]),  # a baseline: the returned policy alone
        ({"td3_eval_return": 2.0, "es_eval_return": 3.0}, "ES mean", ["TD3 actor", "ES mean"]),  # ES-TD3: the ES mean is its curve
        ({"td3_eval_return": 2.0}, "best member", ["TD3 actor", "best member"]),  # a TD3 actor beside another returned policy
        ({"es_eval_return": 3.0}, "ES mean", ["ES mean"]),
    ],
)
def test_the_figure_draws_the_columns_the_run_logs(tmp_path, learners, returned, drawn):
    log = MetricsLog(tmp_path, backend="", experiment_name="test")
    for iteration in range(3):
        log.log({"iteration": iteration, "eval_return": 1.0 + iteration, **learners})
    path = plot_run(tmp_path, SUMMARY, AlgorithmInfo("a", "A", returned))
    assert path.stat().st_size > 0
    fig, ax = pyplot().subplots()
    draw_es_vs_td3(ax, {"metrics": read_metrics(tmp_path / "metrics.csv"), "summary": SUMMARY}, returned)
    assert [line.get_label() for line in ax.get_lines()] == [*drawn, "initial policy"]
    pyplot().close(fig)
