"""Hydra launchers for sweeps: joblib (parallel jobs on one machine) and submitit (Slurm; its local
executor runs here, the Slurm configuration is checked to compose and resolve)."""
import json
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import get_class

from torchrl_esrl.threads import process_cores

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["iterations=1", "env=swimmer", "td3.frames_per_iteration=300"]


def job_interval(run_dir: Path) -> tuple[float, float]:
    """(start, end) of a job: Hydra writes .hydra/config.yaml before the job, the recipe summary.json at its end."""
    return (run_dir / ".hydra" / "config.yaml").stat().st_mtime, (run_dir / "summary.json").stat().st_mtime


@pytest.mark.e2e
def test_joblib_launcher_runs_two_jobs_in_parallel(run_recipe, tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher", reason="pip install -e '.[launchers]' (included in 'dev')")
    result = run_recipe("es_td3.py", "-m", *SMALL, "seed=0,1", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    runs = sorted(p.parent for p in tmp_path.glob("*/summary.json"))
    assert [p.name for p in runs] == ["0", "1"]  # one run directory per job
    assert sorted(json.loads((p / "summary.json").read_text())["seed"] for p in runs) == [0, 1]
    (start0, end0), (start1, end1) = job_interval(runs[0]), job_interval(runs[1])
    assert start0 < end1 and start1 < end0  # the two jobs overlapped in time
    share = max(1, process_cores() // 2)  # two jobs at once: each its half of the cores
    assert [json.loads((p / "summary.json").read_text())["threads"] for p in runs] == [{"td3": share, "es": share}] * 2


@pytest.mark.e2e
def test_an_explicit_thread_count_wins_over_the_jobs_share(run_recipe, tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher", reason="pip install -e '.[launchers]' (included in 'dev')")
    result = run_recipe("td3.py", "-m", *SMALL, "seed=0,1", "td3.num_threads=2", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    assert [json.loads(p.read_text())["threads"] for p in sorted(tmp_path.glob("*/summary.json"))] == [{"td3": 2}] * 2


@pytest.mark.e2e
def test_a_single_run_takes_the_process_cores(run_recipe, tmp_path):
    result = run_recipe("es_td3.py", *SMALL, "iterations=1", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    assert json.loads((tmp_path / "summary.json").read_text())["threads"] == {"td3": process_cores(), "es": process_cores()}


def test_slurm_launcher_config_composes_and_resolves():
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="pip install -e '.[launchers]' (included in 'dev')")
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["hydra/launcher=slurm", "hydra.launcher.partition=cpu"], return_hydra_config=True)
    launcher = cfg.hydra.launcher
    assert get_class(launcher._target_).__name__ == "SlurmLauncher"
    assert launcher.partition == "cpu" and launcher.cpus_per_task == 16 and launcher.timeout_min == 1440
    assert launcher.submitit_folder.endswith(".submitit/%j")


@pytest.mark.e2e
def test_submitit_local_executor_runs_a_job(run_recipe, tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="pip install -e '.[launchers]' (included in 'dev')")
    result = run_recipe("es_td3.py", "-m", *SMALL, "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10", f"hydra.sweep.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((tmp_path / "0" / "summary.json").read_text())
    assert summary["td3_frames"] == 300 and summary["es_frames"] == 800
    assert list((tmp_path / ".submitit").glob("*/*_log.out"))  # submitit's own job folder and logs
