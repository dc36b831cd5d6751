"""The run lifecycle (torchrl_esrl/run/lifecycle.py) on the real recipes in real subprocesses:
determinism, SIGKILL and SIGTERM then resume for every recipe (found in recipes/, tests/conftest.py's
``RECIPES``, each with the overrides it declares beside it), bad configs as one line, NaN faults that
stop the run and keep the last checkpoint loadable, and what users do to runs: rerun finished
ones, kill them in their final stage, damage checkpoints, point a recipe at another run's
directory, ask for tasks or sizes the algorithm or the machine cannot take, fill the disk (a
file-size limit, and a real full filesystem), start a second run in a directory one is writing,
stop runs with SIGTERM and Ctrl-C."""
import hashlib
import importlib.util
import json
import os
import random
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from conftest import RECIPES, ROOT, TINY, load_recipe, outside, own_keys, recipe_command, recipe_of, tiny_overrides

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
# The resume tests run under two thread counts of the process: 1 (ENV), where the run's count differs
# from the phases' (TD3's threads default to the job's cores), and torch's default for the machine.
# A quantity whose rounding follows the thread count, computed under another count after a resume,
# shows as a difference from the uninterrupted run under one of them.
THREADS = {"1": ENV, "default": {k: v for k, v in ENV.items() if k != "OMP_NUM_THREADS"}}


def command(run_dir, *extra, script="es_td3.py"):
    """The recipe with the budget above, what it declares it needs on top of it, then ``extra``."""
    return recipe_command(script, *RESUME, *tiny_overrides(script), *extra, f"hydra.run.dir={run_dir}")


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
    ("td3.precision=fp16", "td3.precision"),
    # Every key of the schema (torchrl_esrl/run/schema.py) with a bounded range or a fixed set of values.
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
    ("es.schedule=parallel", "es.schedule"),
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


@pytest.mark.parametrize(
    "config, override, field",
    [("config", *case) for case in VALUE_ERRORS]
    + [("cem_rl_buffers", "buffer.ratio=[0.5,0.2]", "buffer.ratio"), ("cem_rl_buffers", "threshold.fraction=2", "threshold.fraction")],
)
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


# ---------------------------------------------------------------- every recipe, as users run it
SCRIPTS = sorted(RECIPES)  # recipes/*.py that train; each with its declared overrides (command() above)


@pytest.fixture(scope="module")
def finished(reference, tmp_path_factory):
    """``finished(script, threads="1")``: the run directory of a finished run of that recipe under
    that thread count of :data:`THREADS` (made once)."""
    runs = {("es_td3.py", "1"): reference}

    def get(script, threads="1"):
        if (script, threads) not in runs:
            run_dir = tmp_path_factory.mktemp(script.removesuffix(".py"))
            result = run(run_dir, script=script, env=THREADS[threads])
            assert result.returncode == 0, result.stderr[-3000:]
            runs[script, threads] = run_dir
        return runs[script, threads]

    return get


def tree(run_dir):
    """Every file of a directory and the SHA-256 of its bytes."""
    return {str(p.relative_to(run_dir)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(Path(run_dir).rglob("*")) if p.is_file()}


def summary_without_wall_time(run_dir):
    summary = json.loads((Path(run_dir) / "summary.json").read_text())
    summary.pop("wall_time_s")
    return summary


def killed_after_its_last_checkpoint(source, run_dir):
    """A copy of the finished run ``source`` as a run killed in its final stage leaves it: all
    but ``summary.json``, the last file a run writes."""
    shutil.copytree(source, run_dir)
    (run_dir / "summary.json").unlink()
    return run_dir


def one_line(result):
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr[-3000:]
    return lines[0]


def injected(tool: str, where: str, script: str, run_dir) -> list[str]:
    """``tests/<tool> <where> <script>`` with :func:`command`'s overrides (a kill or a stop it makes itself)."""
    return [sys.executable, str(ROOT / "tests" / tool), where, script, *command(run_dir, script=script)[2:]]  # the overrides, from experiment=tiny on


@pytest.mark.e2e
@pytest.mark.parametrize("threads", list(THREADS))
@pytest.mark.parametrize("script", SCRIPTS)
def test_every_recipe_killed_after_its_first_checkpoint_then_rerun_gives_the_same_records(finished, tmp_path, script, threads):
    """SIGKILL as soon as the recipe's first checkpoint is written (mid-phase where it checkpoints
    mid-phase, else at an iteration's end), then the same command: the uninterrupted run's records,
    under either thread count of the process."""
    env = THREADS[threads]
    killed = subprocess.run(injected("inject_kill.py", "first_checkpoint", script, tmp_path), cwd=ROOT, capture_output=True, text=True, timeout=900, env=env)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-3000:]
    reference = finished(script, threads)
    assert len(checkpoints(tmp_path)) == 1 and len(rows_without_wall_time(tmp_path)) < len(rows_without_wall_time(reference))  # killed mid-run
    result = run(tmp_path, script=script, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    assert rows_without_wall_time(tmp_path) == rows_without_wall_time(reference)
    assert summary_without_wall_time(tmp_path) == summary_without_wall_time(reference)
    record = (tmp_path / script.replace(".py", ".log")).read_text()  # the run's record: both pieces, in order
    assert record.count("] started: ") == 1 and record.count("] resumed at iteration ") == 1 and "] finished: " in record
    assert record.index("] started: ") < record.index("] resumed at iteration ") < record.index("] finished: ")


@pytest.mark.e2e
@pytest.mark.parametrize("script", SCRIPTS)
def test_every_recipe_stopped_by_sigterm_at_its_first_stop_point_resumes_to_the_same_records(finished, tmp_path, script):
    """SIGTERM (a scheduler's stop) as the recipe reaches its first stop point (a TD3 batch, a
    generation, an iteration's end): it stops there in one line with the command that resumes it,
    and that command ends as the uninterrupted run."""
    stopped = subprocess.run(injected("inject_stop.py", "stop_point@1", script, tmp_path), cwd=ROOT, capture_output=True, text=True, timeout=900, env=ENV)
    assert stopped.returncode == 128 + signal.SIGTERM, stopped.stderr[-3000:]
    line = stop_line(stopped.stderr, "SIGTERM")
    assert f"hydra.run.dir={tmp_path}" in line and "Traceback" not in stopped.stderr, line
    reference = finished(script)
    assert len(rows_without_wall_time(tmp_path)) < len(rows_without_wall_time(reference))
    result = run(tmp_path, script=script)
    assert result.returncode == 0, result.stderr[-3000:]
    assert rows_without_wall_time(tmp_path) == rows_without_wall_time(reference)
    assert summary_without_wall_time(tmp_path) == summary_without_wall_time(reference)


ES_GENERATION_1 = 200 // 20 + 1  # RESUME's stop points: its ten TD3 batches, then the first ES generation


@pytest.mark.e2e
def test_a_stop_between_es_generations_checkpoints_the_phase_and_resumes_after_it(reference, tmp_path):
    """SIGTERM as the first ES generation ends: the checkpoint written there holds the generation
    (the run resumes after it, its TD3 evaluation given back, not played again), and the records
    are the uninterrupted run's."""
    stopped = subprocess.run(injected("inject_stop.py", f"stop_point@{ES_GENERATION_1}", "es_td3.py", tmp_path), cwd=ROOT, capture_output=True, text=True, timeout=900, env=ENV)
    assert stopped.returncode == 128 + signal.SIGTERM, stopped.stderr[-3000:]
    assert "after ES generation 1/2" in stop_line(stopped.stderr, "SIGTERM")
    newest = checkpoints(tmp_path)[-1]
    assert json.loads((tmp_path / "checkpoints" / newest / "manifest.json").read_text())["metadata"]["td3_frames"] == 200
    result = run(tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert f"resumed at iteration 1 from {tmp_path / 'checkpoints' / newest}" in (tmp_path / "es_td3.log").read_text()
    assert rows_without_wall_time(tmp_path) == rows_without_wall_time(reference)
    assert summary_without_wall_time(tmp_path) == summary_without_wall_time(reference)


@pytest.mark.e2e
def test_checkpoints_every_es_generation_resume_to_the_same_records(reference, tmp_path):
    """``checkpoint.every_generations=1``: one more checkpoint an iteration (after the first of its two
    generations; the second is the iteration's end); the run resumed from the last iteration's one
    ends as the uninterrupted one."""
    result = run(tmp_path, "checkpoint.every_generations=1", "checkpoint.keep_last=20")
    assert result.returncode == 0, result.stderr[-3000:]
    written = checkpoints(tmp_path)
    at = [(m["iteration"], m["td3_frames"]) for m in (json.loads((tmp_path / "checkpoints" / name / "manifest.json").read_text())["metadata"] for name in written)]
    # every 100 TD3 frames (the second at the TD3 phase's end), after ES generation 1, at the iteration's end
    assert at == [(0, 100), (0, 200), (0, 200), (1, 200), (1, 300), (1, 400), (1, 400), (2, 400)]
    assert rows_without_wall_time(tmp_path) == rows_without_wall_time(reference)
    shutil.rmtree(tmp_path / "checkpoints" / written[-1])  # the last iteration's end: its ES generation checkpoint is left
    (tmp_path / "summary.json").unlink()
    resumed = run(tmp_path, "checkpoint.every_generations=1")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"resumed at iteration 2 from {tmp_path / 'checkpoints' / written[-2]}" in (tmp_path / "es_td3.log").read_text()
    assert rows_without_wall_time(tmp_path) == rows_without_wall_time(reference)
    assert summary_without_wall_time(tmp_path) == summary_without_wall_time(reference)


def _bad_inputs(script: str) -> list[tuple[str, str]]:
    """``(override, field)``: a wrong type and a value outside its check, for a key of the
    recipe's own sections (of every run's keys, for a recipe without sections of its own)."""
    from torchrl_esrl.run.config import schema_fields
    from torchrl_esrl.run.schema import RunConfig

    keys = own_keys(script) or [(key, item) for key, item, _ in schema_fields(RunConfig)]
    key, item = next((key, item) for key, item in keys if item.metadata.get("check", {}).get("kind") == "number")
    return [(f"{key}=abc", key), (f"{key}={outside(item.metadata['check'])}", key)]


@pytest.mark.e2e
@pytest.mark.parametrize("script, override, field", [(script, *bad) for script in SCRIPTS for bad in _bad_inputs(script)])
def test_every_recipe_refuses_bad_input_in_one_line_before_any_work(tmp_path, script, override, field):
    result = run(tmp_path / "run", override, script=script)
    line = one_line(result)
    assert result.returncode == 2 and line.startswith("config error: ") and field in line, line
    assert not (tmp_path / "run").exists()  # refused before the run directory is made


@pytest.mark.e2e
@pytest.mark.parametrize("script", SCRIPTS)
def test_rerunning_a_finished_run_says_so_and_changes_nothing(finished, script):
    run_dir = finished(script)
    before = tree(run_dir)
    result = run(run_dir, script=script)
    assert result.returncode == 0, result.stderr[-3000:]
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("finished:") and str(run_dir / "summary.json") in lines[0], result.stdout
    assert tree(run_dir) == before  # Hydra's .hydra/ and log included: the check runs before Hydra writes


def as_saved_before_sections_were_a_recipes_own(checkpoint: Path) -> None:
    """Rewrite a checkpoint's config as the code before recipes owned their sections saved it: every
    run's config held every section, ``cem: null`` where the recipe had no CEM (its digests made again,
    as that code wrote them)."""
    from torchrl_esrl.run.checkpoint import DIGEST_FILE, DIGESTS, metadata_digest

    manifest_path = checkpoint / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    manifest["metadata"]["config"].setdefault("cem", None)
    manifest_path.write_text(json.dumps(manifest))
    digests_path = checkpoint / manifest["components"][DIGESTS]["path"] / DIGEST_FILE
    digests = json.loads(digests_path.read_text())
    digests["metadata"] = metadata_digest(manifest["metadata"])
    digests_path.write_text(json.dumps(digests))


@pytest.mark.e2e
def test_a_run_checkpointed_when_every_config_held_every_section_resumes(reference, tmp_path):
    """A run whose checkpoint holds a section its recipe does not have (``cem: null``, as every
    ES-TD3Buffers run saved it when every recipe's config held every section) resumes with the same
    command and ends as it would have."""
    run_dir = killed_after_its_last_checkpoint(reference, tmp_path / "run")
    newest = run_dir / "checkpoints" / checkpoints(run_dir)[-1]
    as_saved_before_sections_were_a_recipes_own(newest)
    assert json.loads((newest / "manifest.json").read_text())["metadata"]["config"]["cem"] is None
    result = run(run_dir)
    assert result.returncode == 0 and "cannot be read" not in result.stderr, result.stderr[-3000:]
    assert summary_without_wall_time(run_dir) == summary_without_wall_time(reference)


@pytest.mark.e2e
def test_cem_rl_with_routed_buffers_fills_good_bad_and_noisy_and_learns_at_the_ratio(finished):
    run_dir = finished("cem_rl_buffers.py")
    rows, summary = read_metrics(run_dir / "metrics.csv"), json.loads((run_dir / "summary.json").read_text())
    assert summary["algorithm"] == "cem_rl_buffers" and summary["ratio"] == [0.5, 0.2, 0.3] and summary["buffer_mode"] == "multi"
    last = rows[-1]
    assert last["good_size"] > 0 and last["bad_size"] > 0 and last["noisy_size"] > 0
    assert last["good_size"] + last["bad_size"] + last["noisy_size"] == last["td3_frames"]  # every member's episode, once
    assert last["td3_updates"] > 0 and last["best_return"] >= last["threshold"]


@pytest.mark.e2e
def test_the_cem_alone_plays_the_generations_cem_rl_plays_without_rl(finished, tmp_path):
    """recipes/cem.py is CEM-RL's sepCEM without gradient steps: CEM-RL with ``cem.rl_fraction=0``
    and the same population evaluates the same means, plays the same members and ends the same."""
    cem = finished("cem.py")
    population = next(o for o in tiny_overrides("cem.py") if o.startswith("cem.population_size="))
    result = run(tmp_path, "cem.rl_fraction=0", population, script="cem_rl.py")
    assert result.returncode == 0, result.stderr[-3000:]
    alone, without_rl = read_metrics(cem / "metrics.csv"), read_metrics(tmp_path / "metrics.csv")
    assert len(alone) == len(without_rl) == 2 and not any(row["td3_updates"] for row in without_rl)
    for a, b in zip(alone, without_rl):
        assert (a["es_frames"], a["td3_frames"]) == (b["td3_frames"], 0)  # the same frames, counted as ES frames: no TD3 here
        for column in ("eval_return", "generations", "cem_mean_std", "population_mean_return", "population_max_return"):
            assert a[column] == b[column], column
    assert json.loads((cem / "summary.json").read_text())["final_return"] == json.loads((tmp_path / "summary.json").read_text())["final_return"]


@pytest.mark.e2e
@pytest.mark.parametrize("script", SCRIPTS)
def test_the_summary_names_what_computes_every_component_whatever_the_recipe_calls_it(finished, script):
    """The pieces and threads of ``summary.json`` come from the components a recipe builds, found by
    type: a recipe that evaluates a population (its holdings hold one) is reported as ES-TD3's ES
    collector is, whatever it calls it; one that trains TD3 (it logs TD3 updates) as TD3 is."""
    from torchrl_esrl.envs import env_sizes

    run_dir = finished(script)
    summary = json.loads((run_dir / "summary.json").read_text())
    cfg = compose_tiny(recipe_of(script).config_name, *tiny_overrides(script))
    held = {holding.part for holding in recipe_of(script).holdings(cfg, env_sizes(cfg.env.id, cfg.env.max_episode_steps))}
    evaluates_a_population, trains_td3 = "population" in held, "td3_updates" in read_metrics(run_dir / "metrics.csv")[0]
    pieces, threads = set(summary["pieces"]), set(summary["threads"])
    assert ({"es_forward", "es_physics"} <= pieces and "es" in threads) == evaluates_a_population, summary
    assert ({"td3_loss", "soft_update", "adam"} <= pieces and "td3" in threads) == trains_td3, summary
    assert ({"buffer_writes", "buffer_reads"} <= pieces) == ("buffers" in held), summary


@pytest.mark.e2e
def test_fresh_run_goes_next_to_the_finished_one(reference, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(reference, run_dir)
    before = tree(run_dir)
    result = run(run_dir, "fresh=true")
    assert result.returncode == 0, result.stderr[-3000:]
    assert f"this one starts in {tmp_path / 'run-2'}" in result.stderr
    assert tree(run_dir) == before
    assert rows_without_wall_time(tmp_path / "run-2") == rows_without_wall_time(reference)
    assert summary_without_wall_time(tmp_path / "run-2") == summary_without_wall_time(reference)


# Every recipe killed halfway through writing its summary; the kill in the final evaluation is the lifecycle's, on ES-TD3Buffers.
KILLS = [*((script, "summary_write") for script in SCRIPTS), ("es_td3.py", "final_evaluation")]


@pytest.mark.e2e
@pytest.mark.parametrize("script, where", KILLS)
def test_killed_in_the_final_stage_then_rerun_ends_as_an_uninterrupted_run(finished, tmp_path, script, where):
    killed = subprocess.run(injected("inject_kill.py", where, script, tmp_path), cwd=ROOT, capture_output=True, text=True, timeout=900, env=ENV)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-3000:]
    assert not (tmp_path / "summary.json").exists()
    assert (tmp_path / "summary.json.tmp").exists() == (where == "summary_write")  # half written, never in place
    result = run(tmp_path, script=script)
    assert result.returncode == 0, result.stderr[-3000:]
    reference = finished(script)
    assert rows_without_wall_time(tmp_path) == rows_without_wall_time(reference)
    assert summary_without_wall_time(tmp_path) == summary_without_wall_time(reference)  # frame counts included


FAILS = [("es_td3.py", "figure"), ("td3.py", "figure"), ("es_td3.py", "summary_write"), ("cem_rl.py", "summary_write")]


@pytest.mark.e2e
@pytest.mark.parametrize("script, where", FAILS)
def test_a_final_stage_that_fails_costs_the_figure_or_ends_in_one_line_and_the_same_command_finishes(finished, tmp_path, script, where):
    """A figure that raises costs that figure and one warning line, never the summary; a summary
    that cannot be written ends the run in one line, and a rerun goes straight to the final stage
    (no iteration again) and ends as the uninterrupted run did."""
    failed = subprocess.run(injected("inject_fail.py", where, script, tmp_path), cwd=ROOT, capture_output=True, text=True, timeout=900, env=ENV)
    line = one_line(failed)
    if where == "figure":
        assert failed.returncode == 0 and line.startswith("warning: learning_curve.png was not drawn (KeyError: 'es_eval_return')"), line
        assert not (tmp_path / "learning_curve.png").exists()
    else:
        assert failed.returncode == 2 and line.startswith(f"disk error: No space left on device writing {tmp_path / 'summary.json'}"), line
        assert not (tmp_path / "summary.json").exists()
        result = run(tmp_path, script=script)
        assert result.returncode == 0, result.stderr[-3000:]
        record = (tmp_path / script.replace(".py", ".log")).read_text()
        resumed = record[record.index("] resumed at iteration 3 from "):]
        assert "] iteration " not in resumed and "] finished: " in resumed, resumed
    reference = finished(script)
    assert rows_without_wall_time(tmp_path) == rows_without_wall_time(reference)
    assert summary_without_wall_time(tmp_path) == summary_without_wall_time(reference)


@pytest.mark.e2e
def test_metrics_cut_before_the_last_checkpoint_is_written_back_and_the_run_finishes(finished, tmp_path):
    """metrics.csv cut mid-row below what the checkpoint counts (a crash that lost the page cache,
    a copy cut short): the rerun writes the rows back from the checkpoint's copy, says so in one
    line, and ends as the uninterrupted run did."""
    run_dir = killed_after_its_last_checkpoint(finished("es_td3.py"), tmp_path / "run")
    path = run_dir / "metrics.csv"
    data = path.read_bytes()
    path.write_bytes(data[: data.rindex(b"\n", 0, len(data) - 1) + 20])  # the last row cut after 19 bytes
    with pytest.raises(ValueError, match="line 3 is cut short"):
        read_metrics(path)
    result = run(run_dir)
    assert result.returncode == 0, result.stderr[-3000:]
    said = [line for line in result.stderr.splitlines() if "written back" in line]
    assert len(said) == 1 and said[0].startswith(f"metrics.csv in {run_dir} did not begin with the rows checkpoint-"), result.stderr
    assert path.read_bytes() == data
    assert summary_without_wall_time(run_dir) == summary_without_wall_time(finished("es_td3.py"))


# CEM-RL's second generation takes its gradient steps (F = the first's frames: 4 x 60 and 6 x 60):
# cem_rl.py 120 critic + 240 actor steps per member of 2, cem_rl_buffers.py 120 + 360 per member of 3.
# Step 400 is member 2's critic steps; step 130, member 1's actor steps.
STOPS = [("cem_rl.py", 400, "member 2/2"), ("cem_rl_buffers.py", 130, "member 1/3")]


@pytest.mark.e2e
@pytest.mark.parametrize("threads", list(THREADS))
@pytest.mark.parametrize("script, step, member", STOPS)
def test_cem_rl_stopped_in_its_gradient_steps_checkpoints_there_and_resumes_to_the_same_records(finished, tmp_path, script, step, member, threads):
    env = THREADS[threads]
    stopped = subprocess.run(injected("inject_stop.py", f"gradient_step@{step}", script, tmp_path), cwd=ROOT, capture_output=True, text=True, timeout=900, env=env)
    assert stopped.returncode == 128 + signal.SIGTERM, stopped.stderr[-3000:]
    line = stop_line(stopped.stderr, "SIGTERM")
    assert f", generation under way, {step} gradient steps taken (in CEM-RL's gradient steps, {member})" in line, line
    written = line.split("; checkpoint ")[1].split(" written")[0]
    assert written in checkpoints(tmp_path) and len(rows_without_wall_time(tmp_path)) == 1, line  # mid-iteration 2
    from torchrl_esrl.envs import env_sizes
    from torchrl_esrl.run.capacity import estimate

    cfg = compose_tiny(recipe_of(script).config_name, *tiny_overrides(script))
    disk = int(subprocess.run(["du", "-s", "--block-size=1", str(tmp_path / "checkpoints" / written)], capture_output=True, text=True, check=True).stdout.split()[0])
    assert disk <= estimate(load_recipe(script).holdings(cfg, env_sizes(cfg.env.id, cfg.env.max_episode_steps))).checkpoint  # its population included
    saved = json.loads(next((tmp_path / "checkpoints" / written).glob("components/*-threads/state.json")).read_text())
    saved = {key["value"]: value["value"] for key, value in saved["items"]}  # TorchRL's encoding of {"torch": count}
    if threads == "1":  # the run's count between phases, not the gradient steps' (the job's cores)
        assert saved == {"torch": 1}, saved
    result = run(tmp_path, script=script, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    reference = finished(script, threads)
    assert rows_without_wall_time(tmp_path) == rows_without_wall_time(reference)
    assert summary_without_wall_time(tmp_path) == summary_without_wall_time(reference)


def damage(checkpoint, how):
    """Damage one file of a checkpoint directory as a crash or a bad disk would."""
    if how == "truncated":  # the largest tensor file, cut in half
        path = max((p for p in checkpoint.rglob("*.memmap")), key=lambda p: p.stat().st_size)
        os.truncate(path, path.stat().st_size // 2)
    elif how == "deleted":
        next(checkpoint.glob("components/*-overwrite/state.json")).unlink()
    elif how == "garbage_manifest":
        path = checkpoint / "manifest.json"
        path.write_bytes(random.Random(0).randbytes(path.stat().st_size))
    elif how == "garbage_metadata":  # the TensorDict metadata of TD3's state
        path = next(checkpoint.glob("components/*-td3/state/meta.json"))
        path.write_bytes(random.Random(1).randbytes(path.stat().st_size))
    elif how == "same_length_garbage":  # the largest tensor file, its bytes replaced, its size kept
        path = max((p for p in checkpoint.rglob("*.memmap")), key=lambda p: p.stat().st_size)
        path.write_bytes(random.Random(2).randbytes(path.stat().st_size))


@pytest.mark.e2e
@pytest.mark.parametrize("how", ["truncated", "deleted", "garbage_manifest", "garbage_metadata", "same_length_garbage"])
def test_damaged_newest_checkpoint_falls_back_to_the_previous_one(reference, tmp_path, how):
    run_dir = killed_after_its_last_checkpoint(reference, tmp_path / "run")
    previous, newest = checkpoints(run_dir)[-2:]
    damage(run_dir / "checkpoints" / newest, how)
    result = run(run_dir)
    assert result.returncode == 0, result.stderr[-3000:]
    said = [line for line in result.stderr.splitlines() if "cannot be read" in line]
    assert len(said) == 1 and newest in said[0] and said[0].endswith(f"resuming from {previous}"), result.stderr[-3000:]
    # the rest of the run as one resumed from the previous checkpoint: the uninterrupted run's records
    assert rows_without_wall_time(run_dir) == rows_without_wall_time(reference)
    assert summary_without_wall_time(run_dir) == summary_without_wall_time(reference)


@pytest.mark.e2e
def test_no_readable_checkpoint_stops_with_one_line_and_changes_nothing(reference, tmp_path):
    run_dir = killed_after_its_last_checkpoint(reference, tmp_path / "run")
    for name, how in zip(checkpoints(run_dir), ["deleted", "truncated"]):
        damage(run_dir / "checkpoints" / name, how)
    before = tree(run_dir)
    result = run(run_dir)
    line = one_line(result)
    assert result.returncode == 2 and line.startswith("config error: hydra.run.dir: no checkpoint in") and str(run_dir / "checkpoints") in line
    assert tree(run_dir) == before  # no fresh start on top of the old records


@pytest.mark.e2e
@pytest.mark.parametrize(
    "script, extra, held, asked",
    [
        ("td3.py", [], "an es_td3_buffers run on HalfCheetah-v5", "td3 on HalfCheetah-v5"),
        ("es.py", [], "an es_td3_buffers run on HalfCheetah-v5", "es on HalfCheetah-v5"),
        ("es_td3.py", ["env=walker2d"], "an es_td3_buffers run on HalfCheetah-v5", "es_td3_buffers on Walker2d-v5"),
        ("es_td3.py", ["buffer.mode=shared"], "an es_td3_buffers run on HalfCheetah-v5", "es_td3_shared on HalfCheetah-v5"),
    ],
)
def test_run_directory_of_another_run_is_refused_in_one_line(reference, tmp_path, script, extra, held, asked):
    run_dir = killed_after_its_last_checkpoint(reference, tmp_path / "run")  # what it holds: its checkpoint says
    before = tree(run_dir)
    result = run(run_dir, *extra, script=script)
    line = one_line(result)
    assert result.returncode == 2 and line.startswith("config error: hydra.run.dir:") and f"holds {held}; asked: {asked}" in line, line
    assert tree(run_dir) == before


@pytest.mark.e2e
def test_resuming_another_recipes_run_is_refused_in_one_line(finished, tmp_path):
    td3_run = finished("td3.py")
    before = tree(td3_run)
    result = subprocess.run(recipe_command("es_td3.py", f"resume={td3_run}", f"hydra.run.dir={tmp_path / 'here'}"), cwd=ROOT, capture_output=True, text=True, timeout=300, env=ENV)
    line = one_line(result)
    assert result.returncode == 2 and f"config error: resume: {td3_run} holds a td3 run on HalfCheetah-v5; asked: es_td3_buffers on HalfCheetah-v5" in line, line
    assert tree(td3_run) == before and not (tmp_path / "here").exists()


@pytest.mark.e2e
@pytest.mark.parametrize(
    "script, override, field, words",
    [
        ("es_td3.py", "env.id=CartPole-v1", "env.id", "Discrete(2)"),  # discrete actions
        ("td3.py", "env.id=Blackjack-v1", "env.id", "Discrete(2)"),  # a tuple of discrete observations too
        ("es_td3.py", "buffer.capacity=1000000000000", "buffer.capacity", "of memory"),
        ("es_td3.py", "es.population_size=100000000", "es.population_size", "of memory"),
        ("cem_rl.py", "cem.population_size=100000000", "cem.population_size", "of memory"),
        # values gymnasium.make takes, which fail only when the env is played (the check resets and steps it)
        ("es_td3.py", "++env.kwargs.ctrl_cost_weight=abc", "env.kwargs.ctrl_cost_weight", "fails at HalfCheetah-v5's step 1 (TypeError"),
        ("td3.py", "++env.kwargs.reset_noise_scale=nan", "env.kwargs.reset_noise_scale", "fails at HalfCheetah-v5's reset (OverflowError"),
    ],
)
def test_what_the_algorithm_or_this_machine_cannot_take_is_refused_before_any_work(tmp_path, script, override, field, words):
    run_dir = tmp_path / "run"
    result = run(run_dir, override, script=script)
    line = one_line(result)
    assert result.returncode == 2 and line.startswith(f"config error: {field}:") and words in line and "allowed" in line, line
    assert not run_dir.exists()  # refused before the run directory is made


@pytest.mark.e2e
def test_an_env_that_ends_its_process_is_refused_in_one_line_and_the_run_it_would_resume_finishes_later(finished, tmp_path):
    """A wrapper that aborts its process (as a native crash in MuJoCo would) ends the check's child
    process, not the run's: one line naming the wrapper, and the run directory as it was."""
    run_dir = killed_after_its_last_checkpoint(finished("es_td3.py"), tmp_path / "run")
    before = tree(run_dir)
    tests_first = {**ENV, "PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), ENV.get("PYTHONPATH", "")])}  # tests/native_abort.py
    result = run(run_dir, "env.wrappers=[{_target_:native_abort.AbortAtStep}]", env=tests_first)
    line = one_line(result)
    assert result.returncode == 2 and line.startswith("config error: env.wrappers[0]: native_abort.AbortAtStep ends the process") and "SIGABRT" in line, line
    assert tree(run_dir) == before
    result = run(run_dir)
    assert result.returncode == 0, result.stderr[-3000:]
    assert summary_without_wall_time(run_dir) == summary_without_wall_time(finished("es_td3.py"))


def test_pendulum_takes_the_gym_backend():
    from torchrl_esrl.collectors.backends import default_backend
    from torchrl_esrl.envs import env_sizes

    assert default_backend("Pendulum-v1") == "gym" and default_backend("HalfCheetah-v5") == "mujoco_batch"
    assert env_sizes("Pendulum-v1") == (3, 1, 200)


@pytest.mark.e2e
def test_pendulum_runs_through_the_gym_backend(tmp_path):
    result = subprocess.run(recipe_command("es_td3.py", "env.id=Pendulum-v1", "env.name=pendulum", f"hydra.run.dir={tmp_path}"), cwd=ROOT, capture_output=True, text=True, timeout=900, env=ENV)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["env"] == "Pendulum-v1" and summary["td3_frames"] == 800 and summary["es_frames"] > 0


def compose_tiny(config, *overrides):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        return compose(config, overrides=[TINY, *RESUME, *overrides])


def test_memory_and_disk_checks_name_what_is_needed_what_is_there_and_the_field(tmp_path):
    from torchrl_esrl.envs import env_sizes
    from torchrl_esrl.errors import ConfigError
    from torchrl_esrl.run.capacity import check_capacity, estimate, human

    cfg = compose_tiny("config")
    needed = estimate(load_recipe("es_td3.py").holdings(cfg, env_sizes(cfg.env.id, cfg.env.max_episode_steps)))
    plenty = 10**15
    check_capacity(cfg, needed, tmp_path / "run", memory=plenty, disk=(plenty, tmp_path))
    with pytest.raises(ConfigError) as error:
        check_capacity(cfg, needed, tmp_path / "run", memory=needed.memory_total - 1, disk=(plenty, tmp_path))
    assert str(error.value).startswith("buffer.capacity:") or str(error.value).startswith("actor.hidden:")
    assert human(needed.memory_total) in str(error.value) and human(needed.memory_total - 1) in str(error.value)
    keep = int(cfg.checkpoint.keep_last)
    check_capacity(cfg, needed, tmp_path / "run", memory=plenty, disk=((keep + 1) * needed.checkpoint, tmp_path))
    with pytest.raises(ConfigError) as error:
        check_capacity(cfg, needed, tmp_path / "run", memory=plenty, disk=((keep + 1) * needed.checkpoint - 1, tmp_path))
    message = str(error.value)
    assert message.startswith("hydra.run.dir:") and human((keep + 1) * needed.checkpoint) in message and f"is free at {tmp_path}" in message
    assert "buffer.capacity" in message and "checkpoint.keep_last" in message and "\n" not in message


@pytest.mark.e2e
@pytest.mark.parametrize("script", SCRIPTS)
def test_estimate_matches_the_filled_buffers_and_the_written_checkpoint(finished, script):
    from torchrl.checkpoint import Checkpoint, StateDictCheckpointAdapter

    from torchrl_esrl.data.multibuffer import MultiBuffer, make_multibuffer
    from torchrl_esrl.envs import env_sizes
    from torchrl_esrl.run.capacity import CHECKPOINT_MARGIN, bytes_per_transition, estimate
    from torchrl_esrl.torchrl_private import tensor_storage_data

    run_dir = finished(script)
    cfg = compose_tiny(recipe_of(script).config_name, *tiny_overrides(script))
    sizes = env_sizes(cfg.env.id, cfg.env.max_episode_steps)
    holdings = load_recipe(script).holdings(cfg, sizes)
    needed = estimate(holdings)
    stop_only = sum(held.bytes for held in holdings if held.checkpointed and not held.in_memory)  # a stop's checkpoint adds them (CEM-RL's population)
    newest = run_dir / "checkpoints" / checkpoints(run_dir)[-1]
    per_buffer = int(cfg.buffer.capacity) * bytes_per_transition(sizes.observation_dim, sizes.action_dim)
    unallocated = needed.memory.get("buffers", 0) // per_buffer  # the buffers the recipe builds
    if unallocated:  # the buffers as the run left them, loaded into real ones
        buffer = make_multibuffer(cfg)  # its ratio and readiness as saved
        Checkpoint(buffer=buffer).register_adapter(MultiBuffer, StateDictCheckpointAdapter()).load(newest, components=["buffer"])
        storages = [data for data in (tensor_storage_data(b.storage) for b in buffer.buffers.values()) if data is not None]
        assert storages  # at least one buffer written
        measured = sum(t.numel() * t.element_size() for data in storages for t in data.values(True, True))
        assert measured == len(storages) * per_buffer  # the formula, to the byte
        unallocated -= len(storages)
    disk = int(subprocess.run(["du", "-s", "--block-size=1", str(newest)], capture_output=True, text=True, check=True).stdout.split()[0])
    full = disk + unallocated * per_buffer  # as if every buffer had been written
    assert full + stop_only <= needed.checkpoint and full + stop_only >= 0.8 * (needed.checkpoint - CHECKPOINT_MARGIN), (disk, full, stop_only, needed.checkpoint)


def _file_size_limit(limit):
    return lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))


@pytest.mark.e2e
def test_failed_checkpoint_write_stops_keeps_the_previous_checkpoint_and_resumes(reference, tmp_path):
    first = "checkpoint-000000000100"
    assert start_and_kill(tmp_path, lambda: first in checkpoints(tmp_path)) == -signal.SIGKILL
    kept = tree(tmp_path / "checkpoints" / first)
    # A file-size limit below the size of the next checkpoint's files: its write fails with EFBIG.
    limited = subprocess.run(command(tmp_path), cwd=ROOT, capture_output=True, text=True, timeout=900, env=ENV, preexec_fn=_file_size_limit(64 * 1024))
    line = one_line(limited)
    assert limited.returncode == 2 and line.startswith("checkpoint error: could not write a checkpoint in") and "File too large" in line and f"kept: {first}" in line, line
    assert f"] {line}" in (tmp_path / "es_td3.log").read_text()  # the run's record says what stopped it
    assert checkpoints(tmp_path) == [first] and tree(tmp_path / "checkpoints" / first) == kept
    assert not list((tmp_path / "checkpoints").glob(".*"))  # TorchRL removed its staging folder
    result = run(tmp_path)  # the limit lifted
    assert result.returncode == 0, result.stderr[-3000:]
    assert rows_without_wall_time(tmp_path) == rows_without_wall_time(reference)


def test_a_checkpoint_config_from_before_a_rename_reads_in_todays_names():
    from torchrl_esrl.run.resume import in_todays_names

    old = {"seed": 0, "td3": {"fast": True, "lr": 3e-4}}
    assert in_todays_names(old) == {"seed": 0, "implementation": "fast", "td3": {"fast": None, "lr": 3e-4, "precision": "fp32"}}
    assert in_todays_names({"td3": {"fast": False}})["implementation"] == "reference"
    today = {"implementation": "reference", "td3": {"fast": None, "precision": "fp32"}, "es": {"schedule": "async"}}
    assert in_todays_names(today) == today
    assert in_todays_names({"mode": "async", "es": {"sigma": 0.005}}) == {"mode": None, "es": {"sigma": 0.005, "schedule": "async"}}
    assert old["td3"]["fast"] is True  # the checkpoint's own dict is left as it was


# ---------------------------------------------------------------- one writer, clean stops, a full disk
def wait_for(condition, process, timeout=600):
    deadline = time.monotonic() + timeout
    while not condition():
        assert process.poll() is None, "the run ended before the moment the test waits for"
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def start(run_dir, *extra):
    """The recipe in its own session (so that SIGINT reaches it as Ctrl-C would: to its process group)."""
    return subprocess.Popen(command(run_dir, *extra), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV, start_new_session=True)


@pytest.mark.e2e
def test_a_second_run_in_a_directory_being_written_is_refused_and_a_killed_writer_does_not_block(reference, tmp_path):
    first = start(tmp_path)
    try:
        wait_for(lambda: "checkpoint-000000000100" in checkpoints(tmp_path), first)
        os.killpg(first.pid, signal.SIGSTOP)  # held mid-run, lock and all, however slow the second is to start
        hydra_files = tree(tmp_path / ".hydra")
        second = run(tmp_path)
        line = one_line(second)
        assert second.returncode == 2 and line.startswith(f"config error: hydra.run.dir: {tmp_path} is being written by another run (pid {first.pid} on "), line
        assert "since " in line and "allowed" in line and not second.stdout.strip()
        assert tree(tmp_path / ".hydra") == hydra_files  # Hydra's files are the first run's
    finally:
        os.killpg(first.pid, signal.SIGKILL)  # a writer that dies without a word (kill -9, a lost node)
        first.wait()
    result = run(tmp_path)  # the kernel released the dead writer's lock: the rerun resumes
    assert result.returncode == 0, result.stderr[-3000:]
    assert rows_without_wall_time(tmp_path) == rows_without_wall_time(reference)
    record = (tmp_path / "es_td3.log").read_text()
    assert record.count("] started: ") == 1 and record.count("] resumed at iteration ") == 1  # the refused run wrote no line


def stop_line(stderr, name):
    lines = [line for line in stderr.strip().splitlines() if line.startswith("stopped by")]
    assert len(lines) == 1 and lines[0].startswith(f"stopped by {name} at iteration "), stderr[-3000:]
    return lines[0]


@pytest.mark.e2e
def test_ctrl_c_and_sigterm_stop_cleanly_and_the_same_command_resumes_to_the_same_records(reference, tmp_path):
    # Ctrl-C (SIGINT to the process group) early in iteration 1
    process = start(tmp_path)
    wait_for(lambda: "checkpoint-000000000100" in checkpoints(tmp_path), process)
    os.killpg(process.pid, signal.SIGINT)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGINT, stderr[-3000:]
    line = stop_line(stderr, "SIGINT")
    assert f"to resume: {sys.executable} " in line and line.endswith(f"hydra.run.dir={tmp_path}") and "Traceback" not in stderr
    assert f"] {line}" in (tmp_path / "es_td3.log").read_text()  # the run's record says it too
    # SIGTERM in iteration 2's TD3 phase (after its first mid-phase checkpoint, frame 300: numbered
    # 303, its frames, iterations and ES generations)
    process = start(tmp_path)
    wait_for(lambda: "checkpoint-000000000303" in checkpoints(tmp_path), process)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGTERM, stderr[-3000:]
    line = stop_line(stderr, "SIGTERM")
    if "(in the TD3 phase)" in line:  # the step in progress finished, then a checkpoint of that point
        written = line.split("; checkpoint ")[1].split(" written")[0]
        assert written in checkpoints(tmp_path) and int(written.split("-")[1]) >= 301, line
    assert not list((tmp_path / "checkpoints").glob(".*"))  # no staging folder left
    result = run(tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert rows_without_wall_time(tmp_path) == rows_without_wall_time(reference)
    assert summary_without_wall_time(tmp_path) == summary_without_wall_time(reference)
    record = (tmp_path / "es_td3.log").read_text()
    assert record.count("] stopped by SIGINT at ") == 1 and record.count("] stopped by SIGTERM at ") == 1 and record.count("] resumed at iteration ") == 2


@pytest.fixture
def small_filesystem(tmp_path):
    """``small_filesystem(size)``: a real tmpfs of ``size`` bytes, mounted for the test (root only)."""
    mounts = []

    def mount(size):
        where = tmp_path / f"disk{len(mounts)}"
        where.mkdir()
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)], capture_output=True, text=True)
        if done.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here ({done.stderr.strip() or 'not root'})")
        mounts.append(where)
        return where

    yield mount
    for where in mounts:
        subprocess.run(["umount", "-l", str(where)], check=False)


@pytest.mark.e2e
def test_a_full_filesystem_stops_the_run_keeps_the_last_checkpoint_and_a_rerun_resumes(reference, tmp_path, small_filesystem):
    from torchrl_esrl.envs import env_sizes
    from torchrl_esrl.run.capacity import estimate

    cfg = compose_tiny("config")
    one = estimate(load_recipe("es_td3.py").holdings(cfg, env_sizes(cfg.env.id, cfg.env.max_episode_steps))).checkpoint
    disk = small_filesystem((int(cfg.checkpoint.keep_last) + 1) * one + 8 * 2**20)  # room for the run, as checked before it starts
    run_dir = disk / "run"
    process = start(run_dir)
    filler = disk / "filler"
    try:
        wait_for(lambda: "checkpoint-000000000100" in checkpoints(run_dir), process)
        while True:  # fill the disk while the run is between two checkpoint writes
            process.send_signal(signal.SIGSTOP)
            if not list((run_dir / "checkpoints").glob(".*.stage-*")):
                break
            process.send_signal(signal.SIGCONT)
            time.sleep(0.02)
        kept = checkpoints(run_dir)[-1]
        before = tree(run_dir / "checkpoints" / kept)
        with filler.open("wb") as handle:
            os.posix_fallocate(handle.fileno(), 0, shutil.disk_usage(disk).free - one // 2)
    finally:
        process.send_signal(signal.SIGCONT)
    _, stderr = process.communicate(timeout=300)
    lines = stderr.strip().splitlines()
    assert process.returncode == 2 and len(lines) == 1, stderr[-3000:]
    assert lines[0].startswith(f"checkpoint error: could not write a checkpoint in {run_dir / 'checkpoints'} (No space left on device: a checkpoint needs about "), lines[0]
    assert f"last good checkpoint kept: {kept}" in lines[0] and "rerun the same command" in lines[0]
    assert checkpoints(run_dir)[-1] == kept and tree(run_dir / "checkpoints" / kept) == before
    assert not list((run_dir / "checkpoints").glob(".*"))
    filler.unlink()  # room again
    result = run(run_dir)
    assert result.returncode == 0, result.stderr[-3000:]
    assert rows_without_wall_time(run_dir) == rows_without_wall_time(reference)


def test_a_signal_asks_for_a_stop_a_second_one_or_the_grace_period_stops_at_once(monkeypatch):
    from torchrl_esrl.run import stop as stop_module
    from torchrl_esrl.run.stop import StopOnSignal, Stopped

    stop = StopOnSignal().install()
    try:
        asked = []
        stop.check("nothing asked")  # no stop asked: goes on
        stop.check(lambda: asked.append(1) or "in words")  # a lazy point: its words only on a stop
        assert not asked
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.requested
        with pytest.raises(Stopped) as stopped:
            stop.check(lambda: "at a step boundary", lambda: Path("checkpoint-7"))
        assert stopped.value.signum == signal.SIGTERM and not stopped.value.at_once and stopped.value.written == Path("checkpoint-7")
        assert stopped.value.where == "at a step boundary"
        with pytest.raises(Stopped) as stopped:
            os.kill(os.getpid(), signal.SIGINT)  # a second signal: at once
        assert stopped.value.at_once and stopped.value.signum == signal.SIGTERM
    finally:
        stop.uninstall()
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
    monkeypatch.setattr(stop_module, "STOP_GRACE_S", 0.2)
    stop = StopOnSignal().install()
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        with pytest.raises(Stopped) as stopped:
            time.sleep(5)  # no step boundary: the grace period ends it
        assert stopped.value.at_once
    finally:
        stop.uninstall()


def test_submitits_preemption_handler_is_called_after_the_stop():
    from torchrl_esrl.run.stop import StopOnSignal, Stopped

    called = []
    previous = signal.signal(signal.SIGUSR2, lambda signum, frame: called.append(signum))  # as submitit installs it
    stop = StopOnSignal().install()
    try:
        os.kill(os.getpid(), signal.SIGUSR2)
        assert stop.requested and not called  # the run stops first...
        with pytest.raises(Stopped):
            stop.check("at a step boundary")
        stop.hand_over()
        assert called == [signal.SIGUSR2]  # ...then submitit checkpoints its job and requeues it
    finally:
        stop.uninstall()
        signal.signal(signal.SIGUSR2, previous)


def test_the_resume_command_is_the_command_with_its_run_directory(monkeypatch, tmp_path):
    from torchrl_esrl.run.lifecycle import resume_command

    monkeypatch.setattr(sys, "orig_argv", ["python", "recipes/es_td3.py", "experiment=quick"])
    assert resume_command(tmp_path) == f"python recipes/es_td3.py experiment=quick hydra.run.dir={tmp_path}"
    monkeypatch.setattr(sys, "orig_argv", ["python", "recipes/es_td3.py", f"hydra.run.dir={tmp_path}", "seed=1"])
    assert resume_command(tmp_path) == f"python recipes/es_td3.py hydra.run.dir={tmp_path} seed=1"
    monkeypatch.setattr(sys, "orig_argv", ["python", "recipes/es_td3.py", "fresh=true", "hydra.run.dir=runs/a"])
    assert resume_command(tmp_path / "a-2") == f"python recipes/es_td3.py hydra.run.dir={tmp_path / 'a-2'}"  # not another fresh run
