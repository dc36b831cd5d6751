"""Issue #5 on the real recipe in real subprocesses: determinism, SIGKILL then resume, bad configs
as one line, and NaN faults that stop the run and keep the last checkpoint loadable."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from torchrl_esrl.run.metrics import read_metrics

ROOT = Path(__file__).resolve().parents[1]
# Episodes of 60 steps and checkpoints every 100 TD3 frames: mid-phase checkpoints land mid-episode.
TINY = [
    "experiment=quick",
    "env=halfcheetah",
    "iterations=2",
    "td3.frames_per_iteration=200",
    "td3.frames_per_batch=20",
    "buffer.min_size=64",
    "buffer.batch_size=64",
    "buffer.capacity=2000",
    "es.population_size=4",
    "es.generations_per_iteration=2",
    "env.max_episode_steps=60",
    "eval.episodes=1",
    "eval.final_episodes=1",
    "checkpoint.every_frames=100",
    "logger.progress=false",
]
ENV = {**os.environ, "MUJOCO_QUIET": "1", "OMP_NUM_THREADS": "1"}


def command(run_dir, *extra):
    return [sys.executable, str(ROOT / "recipes" / "es_td3.py"), *TINY, *extra, f"hydra.run.dir={run_dir}"]


def run(run_dir, *extra, env=None):
    return subprocess.run(command(run_dir, *extra), cwd=ROOT, capture_output=True, text=True, timeout=900, env=env or ENV)


def rows_without_wall_time(run_dir):
    return [{k: v for k, v in row.items() if k != "wall_time_s"} for row in read_metrics(Path(run_dir) / "metrics.csv")]


def checkpoints(run_dir):
    directory = Path(run_dir) / "checkpoints"
    return sorted(p.name for p in directory.glob("checkpoint-*")) if directory.exists() else []


def start_and_kill(run_dir, ready, delay=0.0):
    """Start the recipe, SIGKILL it once ``ready()`` holds (plus ``delay`` seconds)."""
    process = subprocess.Popen(command(run_dir), cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=ENV)
    try:
        deadline = time.monotonic() + 900
        while not ready() and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(delay)
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait()
    return process.returncode


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("reference")
    result = run(run_dir)
    assert result.returncode == 0, result.stderr[-3000:]
    return run_dir


def test_same_seed_same_metrics(reference, tmp_path):
    result = run(tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    rows = rows_without_wall_time(tmp_path)
    assert len(rows) == 2 and rows == rows_without_wall_time(reference)
    assert checkpoints(tmp_path)  # checkpoints were written (the two newest kept)


def test_sigkill_at_several_points_then_resume_gives_the_same_metrics(reference, tmp_path):
    # 1) right after the first mid-phase checkpoint (100 TD3 frames, mid-episode)
    assert start_and_kill(tmp_path, lambda: "checkpoint-000000000100" in checkpoints(tmp_path)) == -signal.SIGKILL
    assert not (tmp_path / "metrics.csv").exists()
    # 2) resumed there, killed a moment later (in the TD3 or the ES phase of iteration 0)
    start_and_kill(tmp_path, lambda: True, delay=12.0)
    # 3) resumed, killed as soon as iteration 0's row is written (the checkpoint after it may be missing)
    metrics = tmp_path / "metrics.csv"
    start_and_kill(tmp_path, lambda: metrics.exists() and len(metrics.read_text().splitlines()) >= 2)
    # 4) resumed to the end: the same command in the same run directory
    result = run(tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert rows_without_wall_time(tmp_path) == rows_without_wall_time(reference)
    assert not list((tmp_path / "checkpoints").glob(".*"))  # no staged leftovers


def test_resume_option_continues_a_finished_run_without_rewriting_rows(reference, tmp_path):
    other = tmp_path / "elsewhere"
    result = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "es_td3.py"), f"resume={reference}", "logger.progress=false", f"hydra.run.dir={other}"],
        cwd=ROOT, capture_output=True, text=True, timeout=900, env=ENV,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert len(read_metrics(reference / "metrics.csv")) == 2


VALUE_ERRORS = [
    ("buffer.ratio=[0.5,0.5]", "buffer.ratio"),
    ("buffer.ratio=[0,0,0]", "buffer.ratio"),
    ("buffer.ratio=[-1,1,1]", "buffer.ratio"),
    ("es.sigma=0", "es.sigma"),
    ("td3.tau=-0.1", "td3.tau"),
    ("td3.lr=0", "td3.lr"),
    ("es.lr=0", "es.lr"),
    ("es.population_size=7", "es.population_size"),
    ("es.population_size=0", "es.population_size"),
    ("env.id=HalfCheeta-v5", "HalfCheetah-v5"),  # the closest known name is suggested
    ("buffer.capacity=10", "buffer.capacity"),
    ("buffer.min_size=10", "buffer.min_size"),
    ("iterations=0", "iterations"),
    ("es.generations_per_iteration=0", "es.generations_per_iteration"),
    ("checkpoint.every_frames=-5", "checkpoint.every_frames"),
    ("overwrite.mode=medium", "overwrite.mode"),
    ("overwrite.mix=0", "overwrite.mix"),
    ("overwrite.mix=1.5", "overwrite.mix"),
    ("td3.random_frames=-1", "td3.random_frames"),
]


@pytest.mark.parametrize("override, field", VALUE_ERRORS)
def test_bad_value_gives_a_one_line_error_naming_the_field(tmp_path, override, field):
    from hydra import compose, initialize_config_dir

    from torchrl_esrl.run.checkpoint import prepare_run
    from torchrl_esrl.errors import ConfigError

    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=[*TINY, override])
    with pytest.raises(ConfigError) as error:
        prepare_run(cfg, tmp_path / "run")
    message = str(error.value)
    assert "\n" not in message and field in message and "allowed" in message


@pytest.mark.parametrize(
    "override, field",
    [
        ("td3.lrr=0.1", "td3.lrr"),  # unknown key (typed schema)
        ("es.sigma=abc", "es.sigma"),  # wrong type (typed schema)
        ("es.population_size=7", "es.population_size"),  # value check
        ("resume=/nonexistent/run", "resume"),
    ],
)
def test_bad_config_is_one_line_and_touches_nothing(reference, override, field):
    before = {p: p.stat().st_mtime_ns for p in reference.rglob("*")}
    result = subprocess.run(command(reference, override), cwd=ROOT, capture_output=True, text=True, timeout=300, env=ENV)
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and field in lines[0] and lines[0].startswith("config error"), result.stderr
    assert {p: p.stat().st_mtime_ns for p in reference.rglob("*")} == before  # nothing written or lost


def test_other_config_in_a_run_directory_with_a_checkpoint_is_rejected(reference):
    result = run(reference, "td3.lr=0.001")
    assert result.returncode != 0 and "td3.lr" in result.stderr and len(result.stderr.strip().splitlines()) == 1, result.stderr


def test_unwritable_output_directory_is_rejected(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    result = run(blocker / "run")
    assert result.returncode != 0 and "hydra.run.dir" in result.stderr and len(result.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("where", ["es_mean", "td3_batch"])
def test_injected_nan_stops_the_run_and_keeps_the_last_checkpoint(tmp_path, where):
    result = run(tmp_path, "iterations=3", env={**ENV, "ESRL_INJECT_NAN": f"{where}@1"})
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    assert lines and lines[-1].startswith("numerical fault:") and "Traceback" not in result.stderr, result.stderr[-2000:]
    assert len(read_metrics(tmp_path / "metrics.csv")) == 1  # iteration 1 never finished
    latest = max((tmp_path / "checkpoints").glob("checkpoint-*"))
    # iteration 0's boundary checkpoint (201), or a mid-phase one of iteration 1 before the fault
    assert int(latest.name.split("-")[1]) >= 201
    from torchrl.checkpoint import Checkpoint

    manifest = Checkpoint.manifest(latest)
    assert manifest["metadata"]["iteration"] == 1
    # The checkpoint loads, and its ES mean is finite: resuming without the injection completes.
    result = run(tmp_path, "iterations=3")
    assert result.returncode == 0, result.stderr[-3000:]
    assert len(read_metrics(tmp_path / "metrics.csv")) == 3
