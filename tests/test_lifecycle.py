"""The run lifecycle (torchrl_esrl/run/lifecycle.py) on the real recipes in real subprocesses:
determinism, SIGKILL then resume for every recipe, bad configs as one line, and NaN faults that
stop the run and keep the last checkpoint loadable."""
import importlib.util
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from conftest import ROOT, TINY, recipe_command

from torchrl_esrl.run.metrics import read_metrics

# On top of the tiny preset: episodes of 60 steps and checkpoints every 100 TD3 frames, so
# mid-phase checkpoints land mid-episode.
RESUME = [
    "env=halfcheetah",
    "td3.frames_per_iteration=200",
    "td3.frames_per_batch=20",
    "buffer.min_size=64",
    "buffer.batch_size=64",
    "buffer.capacity=2000",
    "env.max_episode_steps=60",
    "eval.episodes=1",
    "eval.final_episodes=1",
    "checkpoint.every_frames=100",
]
WANDB = importlib.util.find_spec("wandb") is not None
CUDA = torch.cuda.is_available()
ENV = {**os.environ, "MUJOCO_QUIET": "1", "OMP_NUM_THREADS": "1"}


def command(run_dir, *extra, script="es_td3.py"):
    return recipe_command(script, *RESUME, *extra, f"hydra.run.dir={run_dir}")


def run(run_dir, *extra, env=None, script="es_td3.py"):
    return subprocess.run(command(run_dir, *extra, script=script), cwd=ROOT, capture_output=True, text=True, timeout=900, env=env or ENV)


def rows_without_wall_time(run_dir):
    path = Path(run_dir) / "metrics.csv"
    return [{k: v for k, v in row.items() if k != "wall_time_s"} for row in read_metrics(path)] if path.exists() else []


def checkpoints(run_dir):
    directory = Path(run_dir) / "checkpoints"
    return sorted(p.name for p in directory.glob("checkpoint-*")) if directory.exists() else []


def start_and_kill(run_dir, ready, delay=0.0, *extra, script="es_td3.py"):
    """Start the recipe, SIGKILL it once ``ready()`` holds (plus ``delay`` seconds)."""
    process = subprocess.Popen(command(run_dir, *extra, script=script), cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=ENV)
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


@pytest.mark.e2e
def test_same_seed_same_metrics(reference, tmp_path):
    result = run(tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    rows = rows_without_wall_time(tmp_path)
    assert len(rows) == 2 and rows == rows_without_wall_time(reference)
    assert checkpoints(tmp_path)  # checkpoints were written (the two newest kept)


@pytest.mark.e2e
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


@pytest.mark.e2e
def test_resume_option_continues_a_finished_run_without_rewriting_rows(reference, tmp_path):
    other = tmp_path / "elsewhere"
    result = subprocess.run(recipe_command("es_td3.py", f"resume={reference}", f"hydra.run.dir={other}"), cwd=ROOT, capture_output=True, text=True, timeout=900, env=ENV)
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
    ("td3.num_threads=0", "td3.num_threads"),
    # Every key of conf/config.yaml with a bounded range or a fixed set of values.
    ("seed=-1", "seed"),
    ("experiment_name=''", "experiment_name"),
    ("device=cuda:99", "device"),
    ("device=tpu", "device"),
    ("env.max_episode_steps=0", "env.max_episode_steps"),
    ("td3.frames_per_iteration=0", "td3.frames_per_iteration"),
    ("td3.frames_per_batch=0", "td3.frames_per_batch"),
    ("td3.frames_per_batch=7", "td3.frames_per_batch"),
    ("td3.updates_per_frame=0", "td3.updates_per_frame"),
    ("td3.gamma=1.5", "td3.gamma"),
    ("td3.gamma=-0.1", "td3.gamma"),
    ("td3.tau=0", "td3.tau"),
    ("td3.tau=1.5", "td3.tau"),
    ("td3.policy_noise=-0.2", "td3.policy_noise"),
    ("td3.noise_clip=-0.5", "td3.noise_clip"),
    ("td3.policy_delay=0", "td3.policy_delay"),
    ("td3.exploration_noise=-0.1", "td3.exploration_noise"),
    ("td3.loss_function=huber", "td3.loss_function"),
    ("td3.critic_hidden=[]", "td3.critic_hidden"),
    ("td3.critic_hidden=[256,0]", "td3.critic_hidden"),
    ("td3.critic_activation=gelu", "td3.critic_activation"),
    ("actor.hidden=[-1]", "actor.hidden"),
    ("actor.activation=sigmoid", "actor.activation"),
    ("es.weight_decay=-1", "es.weight_decay"),
    ("es.fitness_shaping=rank", "es.fitness_shaping"),
    ("es.backend=gpu", "es.backend"),
    ("es.sigma=nan", "es.sigma"),
    ("buffer.batch_size=0", "buffer.batch_size"),
    ("buffer.min_size=3000", "buffer.min_size"),  # K above capacity: TD3 would never start
    ("buffer.mode=split", "buffer.mode"),
    ("threshold.fraction=1.2", "threshold.fraction"),
    ("overwrite.window=0", "overwrite.window"),
    ("eval.episodes=0", "eval.episodes"),
    ("eval.final_episodes=0", "eval.final_episodes"),
    ("mode=parallel", "mode"),
    ("ray.num_workers=0", "ray.num_workers"),
    ("ray.num_cpus_per_worker=0", "ray.num_cpus_per_worker"),
    ("ray.worker_backend=ray", "ray.worker_backend"),
    ("logger.backend=foo", "logger.backend"),
    ("logger.backend=wandb", "logger.backend"),  # skipped where wandb is installed
    ("checkpoint.keep_last=0", "checkpoint.keep_last"),
    ("ray.address=somewhere", "ray.address"),
    ("ray.address=host:port", "ray.address"),
    ("ray.worker_kwargs=3", "ray.worker_kwargs"),
]


CEM_VALUE_ERRORS = [  # conf/cem_rl.yaml's own section
    ("cem.population_size=1", "cem.population_size"),
    ("cem.rl_fraction=1.5", "cem.rl_fraction"),
    ("cem.elite_fraction=0", "cem.elite_fraction"),
    ("cem.sigma_init=0", "cem.sigma_init"),
    ("cem.damping_init=-1", "cem.damping_init"),
    ("cem.damping_end=-1", "cem.damping_end"),
    ("cem.damping_tau=2", "cem.damping_tau"),
    ("cem.start_frames=-1", "cem.start_frames"),
]


@pytest.mark.parametrize("config, override, field", [("config", *case) for case in VALUE_ERRORS] + [("cem_rl", *case) for case in CEM_VALUE_ERRORS])
def test_bad_value_gives_a_one_line_error_naming_the_field(tmp_path, config, override, field):
    from hydra import compose, initialize_config_dir

    from torchrl_esrl.errors import ConfigError
    from torchrl_esrl.run.resume import prepare_run

    if override == "logger.backend=wandb" and WANDB:
        pytest.skip("wandb is installed")
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config, overrides=[TINY, *RESUME, override])
    with pytest.raises(ConfigError) as error:
        prepare_run(cfg, tmp_path / "run")
    message = str(error.value)
    assert "\n" not in message and field in message and "allowed" in message


@pytest.mark.e2e
@pytest.mark.parametrize(
    "override, field",
    [
        ("td3.lrr=0.1", "td3.lrr"),  # unknown key (typed schema)
        ("es.sigma=abc", "es.sigma"),  # wrong type (typed schema)
        ("es.population_size=7", "es.population_size"),  # value check
        ("resume=/nonexistent/run", "resume"),
        ("td3.tau=1.5", "td3.tau"),  # TorchRL's SoftUpdate would raise deep inside
        ("td3.gamma=1.01", "td3.gamma"),  # would train
        ("logger.backend=foo", "logger.backend"),  # TorchRL's get_logger would raise deep inside
        pytest.param("logger.backend=wandb", "logger.backend", marks=pytest.mark.skipif(WANDB, reason="wandb is installed")),
        pytest.param("device=cuda", "device", marks=pytest.mark.skipif(CUDA, reason="CUDA is available")),
        ("td3.loss_function=huber", "td3.loss_function"),
    ],
)
def test_bad_config_is_one_line_and_touches_nothing(reference, override, field):
    before = {p: p.stat().st_mtime_ns for p in reference.rglob("*")}
    result = subprocess.run(command(reference, override), cwd=ROOT, capture_output=True, text=True, timeout=300, env=ENV)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and field in lines[0] and lines[0].startswith("config error"), result.stderr
    assert {p: p.stat().st_mtime_ns for p in reference.rglob("*")} == before  # nothing written or lost


@pytest.mark.e2e
def test_other_config_in_a_run_directory_with_a_checkpoint_is_rejected(reference):
    result = run(reference, "td3.lr=0.001")
    assert result.returncode != 0 and "td3.lr" in result.stderr and len(result.stderr.strip().splitlines()) == 1, result.stderr


@pytest.mark.e2e
@pytest.mark.parametrize(
    "recipe, where",
    [
        ("es_td3", "under_a_file"),
        ("es_td3", "read_only"),  # /proc/<dir> cannot be created, even by root
        ("td3", "under_a_file"),
        ("cem_rl", "read_only"),
    ],
)
def test_output_directory_that_cannot_be_created_is_rejected(tmp_path, recipe, where):
    blocker = tmp_path / "file"
    blocker.write_text("")
    run_dir = blocker / "run" if where == "under_a_file" else Path("/proc/esrl_run_dir_test/run")
    result = subprocess.run([sys.executable, str(ROOT / "recipes" / f"{recipe}.py"), TINY, f"hydra.run.dir={run_dir}"], cwd=ROOT, capture_output=True, text=True, timeout=300, env=ENV)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("config error: hydra.run.dir"), result.stderr[-2000:]


@pytest.mark.e2e
@pytest.mark.parametrize("where", ["es_mean", "td3_batch"])
def test_injected_nan_stops_the_run_and_keeps_the_last_checkpoint(tmp_path, where):
    injected = [sys.executable, str(ROOT / "tests" / "inject_nan.py"), f"{where}@1", TINY, *RESUME, "iterations=3", f"hydra.run.dir={tmp_path}"]
    result = subprocess.run(injected, cwd=ROOT, capture_output=True, text=True, timeout=900, env=ENV)
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


# The baselines resume too: a mid-phase checkpoint of TD3; iteration boundaries of ES and CEM-RL.
BASELINES = [
    ("td3.py", [], "checkpoint-000000000100"),
    ("es.py", ["iterations=4"], "checkpoint-000000000001"),
    ("cem_rl.py", ["iterations=4", "cem.population_size=4", "cem.start_frames=0"], "checkpoint-000000000001"),
]


@pytest.mark.e2e
@pytest.mark.parametrize("script, extra, first_checkpoint", BASELINES, ids=[b[0] for b in BASELINES])
def test_baseline_killed_then_resumed_gives_the_same_metrics(tmp_path, script, extra, first_checkpoint):
    reference = tmp_path / "reference"
    result = run(reference, *extra, script=script)
    assert result.returncode == 0, result.stderr[-3000:]
    killed = tmp_path / "killed"
    returncode = start_and_kill(killed, lambda: first_checkpoint in checkpoints(killed), 0.0, *extra, script=script)
    assert returncode == -signal.SIGKILL
    assert len(rows_without_wall_time(killed)) < len(rows_without_wall_time(reference))  # killed mid-run
    result = run(killed, *extra, script=script)
    assert result.returncode == 0, result.stderr[-3000:]
    assert rows_without_wall_time(killed) == rows_without_wall_time(reference)
