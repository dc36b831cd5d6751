"""benchmarks.full_scale: a real run continued from a checkpoint at an iteration boundary, one iteration
timed with the working tree's recipe and a commit's, the run itself left as it was."""
import hashlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import full_scale, run_floor

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.e2e


def _digest(folder: Path) -> dict:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_an_iteration_continued_from_a_real_checkpoint_is_timed_and_is_the_runs_own(tmp_path):
    run_dir = tmp_path / "run"
    command = [sys.executable, "recipes/es_td3.py", "experiment=tiny", "iterations=3", "checkpoint.keep_last=10", "td3.num_threads=1", f"hydra.run.dir={run_dir}"]
    assert subprocess.run(command, cwd=ROOT, capture_output=True, timeout=900).returncode == 0
    assert sorted(full_scale.boundary_checkpoints(run_dir)) == [1, 2, 3]
    before = _digest(run_dir)
    worktrees = subprocess.run(["git", "worktree", "list"], cwd=ROOT, capture_output=True, text=True).stdout
    out = tmp_path / "full_scale.json"
    full_scale.main([str(run_dir), "--base", "HEAD", "--rounds", "2", "--iteration", "1", "--out", str(out)])
    report = json.loads(out.read_text())
    assert _digest(run_dir) == before  # the run was only read
    assert report["recipe"] == "recipes/es_td3.py" and report["from_iteration"] == 1
    with (run_dir / "metrics.csv").open() as f:
        original = [line.split(",") for line in f.read().splitlines()]
    column = original[0].index("eval_return")
    work = {key: int(original[2][original[0].index(key)]) - int(original[1][original[0].index(key)]) for key in full_scale.WORK_COLUMNS}
    assert work["td3_frames"] == 400 and work["es_frames"] > 0 and work["td3_updates"] > 0
    for name in ("now", "base"):
        assert len(report["times"][name]) == 2
        for timed in report["times"][name]:
            assert timed["iteration"] == 1 and 0 < timed["iteration_s"] < timed["process_s"]
            assert timed["eval_return"] == float(original[2][column])  # the second iteration, as the run itself had it
            assert timed["work"] == work  # the iteration's own frames and updates
    bounds = json.loads((ROOT / "benchmarks/results/floor_2026-12-05/bounds.json").read_text())  # a real sitting's floor
    floor = run_floor.against_floor(report, bounds)
    assert floor["env"] == "HalfCheetah-v5" and len(floor["iterations"]) == 2
    for row in floor["iterations"]:
        assert row["floor_s"] == pytest.approx(row["es_physics_s"] + row["td3_physics_s"] + row["td3_products_s"])
        assert row["over_floor"] == pytest.approx(row["iteration_s"] / row["floor_s"])
    es_population = json.loads((ROOT / "benchmarks/results/floor_2026-12-05/es_population_shared_center.json").read_text())
    raw = es_population["envs"]["HalfCheetah-v5"]["raw"]["steps_per_s"]
    whole_episodes = run_floor.against_floor(report, bounds, es_population)
    assert whole_episodes["physics"].startswith("es_population")
    for row in whole_episodes["iterations"]:
        assert row["es_physics_s"] == pytest.approx(work["es_frames"] / raw)  # both cores at the raw rate
        assert row["td3_physics_s"] == pytest.approx(work["td3_frames"] * 2 / raw)  # one core
    replay = es_population["envs"]["HalfCheetah-v5"]["raw_replay"]["steps_per_s"]
    replayed = run_floor.against_floor(report, bounds, es_population, physics="raw_replay")
    assert replayed["physics"].startswith("es_population: raw_replay") and replay != raw
    for row in replayed["iterations"]:
        assert row["es_physics_s"] == pytest.approx(work["es_frames"] / replay)
    assert len(report["ratio_now_over_base"]["per_round"]) == 2
    with pytest.raises(SystemExit, match="--iteration: 3 has no checkpoint"):  # the last iteration leaves none to run
        full_scale.run(run_dir, iteration=3)
    assert subprocess.run(["git", "worktree", "list"], cwd=ROOT, capture_output=True, text=True).stdout == worktrees  # the base's removed


def test_run_floor_refuses_a_physics_rate_without_its_record(tmp_path, capsys):
    """``--physics`` picks one of ``--es-population``'s rates: without that record, one line and exit 2."""
    with pytest.raises(SystemExit) as exit_info:
        run_floor.main(["--full-scale", str(tmp_path / "f.json"), "--bounds", str(tmp_path / "b.json"), "--physics", "raw_replay"])
    assert exit_info.value.code == 2
    assert "--physics: needs --es-population" in capsys.readouterr().err
