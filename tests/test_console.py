"""What a run prints (torchrl_esrl/run/console.py): outside a terminal, one plain line per iteration;
in its run directory's <recipe>.log, the same lines with their times; on a fresh machine, only the
project's own lines."""
import os
import re
import subprocess

import pytest

from tests.conftest import recipe_command, ROOT
from torchrl_esrl.run.console import iteration_line

ROW = {"iteration": 2, "td3_frames": 3000, "es_frames": 4521, "eval_return": 183.04, "td3_eval_return": 61.2, "es_eval_return": 183.04, "overwritten": False, "wall_time_s": 3725.9}


def test_iteration_line_names_frames_returns_decision_and_time():
    assert iteration_line(ROW, 20, 6.0) == (
        "iteration 3/20 | TD3 frames 3000 | ES frames 4521 | return 183.0, TD3 actor 61.2, ES mean 183.0 (initial 6.0) | ES mean kept | elapsed 1:02:05"
    )
    baseline = {k: ROW[k] for k in ("iteration", "td3_frames", "es_frames", "eval_return", "wall_time_s")}
    assert iteration_line(baseline, 20, None) == "iteration 3/20 | TD3 frames 3000 | ES frames 4521 | return 183.0 | elapsed 1:02:05"


@pytest.mark.e2e
@pytest.mark.parametrize("script", ["es_td3.py", "td3.py"])
def test_output_to_a_file_has_one_plain_line_per_iteration(script, tmp_path):
    log = tmp_path / "log.txt"
    with log.open("w") as out:  # as nohup, Slurm and `> log` do: stdout and stderr to a file
        result = subprocess.run(recipe_command(script, "logger.progress=true", f"hydra.run.dir={tmp_path / 'run'}"), cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, timeout=600)
    text = log.read_text()
    assert result.returncode == 0, text[-3000:]
    assert "\r" not in text  # no carriage-return updates of a progress bar
    lines = [line for line in text.splitlines() if line.startswith("iteration ")]
    assert [re.match(r"iteration (\d+)/2 \| TD3 frames (\d+) \|", line).groups() for line in lines] == [("1", "400"), ("2", "800")]
    assert all("| elapsed " in line for line in lines)
    record = (tmp_path / "run" / script.replace(".py", ".log")).read_text()  # Hydra's job log: the run's record
    messages = re.findall(r"^\[\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}\] (.*)$", record, flags=re.MULTILINE)  # a time, then the line
    assert messages[0].startswith("started: ") and ", seed 0, 2 iterations" in messages[0], record[:500]
    assert [m for m in messages if m.startswith("iteration ")] == lines
    assert messages[-1].startswith("finished: ") and "mean return over" in record


@pytest.mark.e2e
def test_a_first_run_on_a_fresh_machine_prints_only_the_projects_lines(tmp_path):
    """A fresh MPLCONFIGDIR: matplotlib builds its font cache during the run (its INFO record goes to
    the run's log file, not to the console)."""
    fresh = tmp_path / "matplotlib"
    env = {**os.environ, "MPLCONFIGDIR": str(fresh)}
    result = subprocess.run(recipe_command("es.py", f"hydra.run.dir={tmp_path / 'run'}"), cwd=ROOT, capture_output=True, text=True, timeout=600, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    assert list(fresh.glob("fontlist-*.json"))  # the font cache was built by this run
    lines = result.stdout.strip().splitlines()
    assert result.stderr == "" and lines[0].startswith("pieces: ") and lines[1].startswith("es on HalfCheetah-v5, seed 0: 2 iterations"), result.stdout
    assert not [line for line in lines if re.match(r"^\[[^]]*\]\[[\w.]+\]\[[A-Z]+\]", line)], result.stdout  # no library's log record
    assert "fontManager" in (tmp_path / "run" / "es.log").read_text()
