"""The Hydra recipe end to end, in a real subprocess, on real MuJoCo with a tiny budget."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

from torchrl_esrl.run.metrics import METRIC_COLUMNS, read_metrics

ROOT = Path(__file__).resolve().parents[1]
TINY = [
    "experiment=quick",
    "iterations=2",
    "td3.frames_per_iteration=600",
    "td3.frames_per_batch=50",
    "buffer.min_size=256",
    "buffer.capacity=5000",
    "es.population_size=4",
    "es.generations_per_iteration=2",
    "env.max_episode_steps=100",
    "eval.episodes=2",
    "eval.final_episodes=2",
    "logger.progress=false",
]


def run_recipe(*overrides, script="es_td3.py"):
    return subprocess.run(
        [sys.executable, str(ROOT / "recipes" / script), *overrides],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )


def test_quick_preset_shortened_writes_every_output(tmp_path):
    result = run_recipe(*TINY, "env=halfcheetah", "buffer.renormalize=true", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    rows = read_metrics(tmp_path / "metrics.csv")
    assert len(rows) == 2
    assert set(METRIC_COLUMNS) <= set(rows[0])
    assert [r["iteration"] for r in rows] == [0, 1]
    assert [r["td3_frames"] for r in rows] == [600, 1200]
    assert rows[-1]["es_frames"] > rows[0]["es_frames"] > 0
    assert rows[-1]["good_size"] + rows[-1]["bad_size"] == rows[-1]["es_frames"]  # every ES step routed
    assert rows[-1]["noisy_size"] == 1200
    # renormalised readiness: noisy holds K=256 after 300 frames (batches of 50), then one update per frame
    assert [r["td3_updates"] for r in rows] == [350, 950]
    assert rows[-1]["threshold"] <= rows[-1]["best_return"]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["env"] == "HalfCheetah-v5" and summary["ratio"] == [0.5, 0.2, 0.3]
    for key in ("final_es_mean_return", "final_td3_actor_return", "td3_frames", "es_frames", "wall_time_s"):
        assert key in summary
    assert (tmp_path / "es_mean.pt").exists() and (tmp_path / "td3_actor.pt").exists()
    scalars = list((tmp_path / "logs").rglob("td3_eval_return.csv"))
    assert scalars and scalars[0].read_text().strip()  # TorchRL's csv logger got the values


def test_multirun_sweeps_the_ratio_one_directory_per_ratio(tmp_path):
    result = run_recipe("-m", *TINY, "iterations=1", "env=swimmer", "buffer.ratio=[0.5,0.2,0.3],[0.34,0.33,0.33]", f"hydra.sweep.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    summaries = sorted(tmp_path.glob("*/summary.json"))
    assert len(summaries) == 2
    ratios = sorted(json.loads(s.read_text())["ratio"] for s in summaries)
    assert ratios == [[0.34, 0.33, 0.33], [0.5, 0.2, 0.3]]


@pytest.mark.parametrize(
    "override, field",
    [
        ("buffer.ratio=[0.5,0.5]", "buffer.ratio"),
        ("buffer.ratio=[-1,1,1]", "buffer.ratio"),
        ("es.sigma=0", "es.sigma"),
        ("es.population_size=7", "es.population_size"),
        ("env.id=Walker3-v5", "env.id"),
        ("buffer.min_size=10", "buffer.min_size"),
        ("buffer.mode=sharde", "buffer.mode"),
    ],
)
def test_bad_config_fails_fast_with_one_line(tmp_path, override, field):
    result = run_recipe(override, "logger.progress=false", f"hydra.run.dir={tmp_path}")
    assert result.returncode != 0
    message = result.stderr.strip().splitlines()
    assert len(message) == 1 and field in message[0], result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "metrics.csv").exists()
