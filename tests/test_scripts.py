"""The experiment scripts (scripts/), run for real on MuJoCo with tiny budgets: what they record,
what they skip on a second call, what they delete."""
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from torchrl_esrl.report.timing import read_attempts

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.e2e


def _processor() -> str:
    """scripts/processor.sh's text for this machine, which the run scripts record beside each attempt."""
    return subprocess.run([str(ROOT / "scripts" / "processor.sh")], capture_output=True, text=True, check=True).stdout.strip()


def _script(name: str, *args: str, **environment: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHON": sys.executable, **environment}
    return subprocess.run(["bash", str(ROOT / "scripts" / name), *args], cwd=ROOT, capture_output=True, text=True, timeout=900, env=env)


def test_experiment_set_starts_over_a_run_without_a_checkpoint_records_it_deletes_its_checkpoints_and_skips_it_next_time(tmp_path):
    work, results = tmp_path / "work", tmp_path / "results"
    tiny = ("iterations=1", "es.population_size=4", "env.max_episode_steps=50", "eval.episodes=1", "eval.final_episodes=1")
    call = lambda: _script("multibuffer_experiments.sh", str(work), "1", *tiny, SET="miniature", RESULTS=str(results), ONLY="^swimmer es es.py 0$")
    (work / "swimmer").mkdir(parents=True)
    held = "pause 2026-01-01T00:00:00Z\nresume 2026-01-01T00:05:00Z\n"
    (work / "swimmer" / "es_seed0.pauses").write_text(held)  # as scripts/pause_runs.sh leaves it
    killed = work / "swimmer" / "es_seed0"  # killed while writing its first checkpoint: a row, a staging folder, no checkpoint
    (killed / "checkpoints" / ".checkpoint-000000000001.tmp").mkdir(parents=True)
    (killed / "metrics.csv").write_text("iteration,td3_frames\n0,0\n")
    (killed / "timing.txt").write_text("swimmer es_seed0: exit 137 after 15 s on commit abc\n")
    alive = "swimmer es_seed0: exit killed after 20 s on commit def started 2026-01-01T00:10:00Z load_mean 1.00 load_max 1.50"
    (work / "swimmer" / "es_seed0.alive").write_text(alive + "\n")  # an attempt that ended with its script: its last line
    first = call()
    assert first.returncode == 0, first.stdout + first.stderr
    record = results / "swimmer" / "es_seed0"
    assert sorted(p.name for p in record.iterdir()) == ["config.yaml", "metrics.csv", "pauses.txt", "run.log", "summary.json", "timing.txt"]
    assert (record / "pauses.txt").read_text() == held
    assert json.loads((record / "summary.json").read_text())["env"] == "Swimmer-v5"
    commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    started_over, ended_with_script, attempt = (record / "timing.txt").read_text().splitlines()  # the killed attempts, marked, then the run
    assert started_over == "swimmer es_seed0: exit 137 after 15 s on commit abc (started over)"
    assert ended_with_script == alive + " (started over)" and not (work / "swimmer" / "es_seed0.alive").exists()
    words = attempt.split()
    assert attempt.startswith("swimmer es_seed0: exit 0 after ") and words[words.index("commit") + 1] == commit
    assert words[words.index("started") + 1].endswith("Z") and float(words[words.index("load_max") + 1]) >= float(words[words.index("load_mean") + 1]) > 0
    assert attempt.endswith(f" cpu {_processor()}") and [a.cpu for a in read_attempts(record)] == ["", "", _processor()]
    assert "finished:" in (record / "run.log").read_text()  # the run's own log, each line timed
    assert not (record / "arithmetic.txt").exists()  # its kept attempt ran on one commit
    run_dir = work / "swimmer" / "es_seed0"
    assert (run_dir / "summary.json").exists() and not (run_dir / "checkpoints").exists()
    second = call()
    assert second.returncode == 0 and "swimmer es_seed0: recorded, skipped" in second.stdout
    assert len((record / "timing.txt").read_text().splitlines()) == 3


def test_the_processor_script_names_this_machines_processor():
    """scripts/processor.sh against the first processor of /proc/cpuinfo, read here."""
    cpuinfo = Path("/proc/cpuinfo")
    first = cpuinfo.read_text().split("\n\n")[0] if cpuinfo.exists() else ""
    field = {key: re.search(rf"^{key}\s*: (.*)$", first, re.M) for key in ("cpu family", "model", "model name")}
    if not all(field.values()):  # no /proc/cpuinfo, or one that names no family and model (some ARM machines)
        assert _processor() == "unknown"
    else:
        assert _processor() == f"family {field['cpu family'][1].strip()} model {field['model'][1].strip()} {field['model name'][1].strip()}"


def test_paper_run_records_each_piece_a_killed_one_too_and_never_reruns_a_finished_run(tmp_path):
    run_dir, results, report = tmp_path / "run", tmp_path / "records", tmp_path / "report"
    killed = "piece 0 commit abc start 2026-01-01T00:00:00Z seconds 40 peak_rss_mib 900"
    (tmp_path / "run.piece0.alive").write_text(killed + "\n")  # what a piece killed with its session leaves
    call = lambda: _script("paper_run.sh", str(run_dir), "experiment=tiny", "td3.num_threads=1", RESULTS=str(results), REPORT=str(report))
    first = call()
    assert first.returncode == 0, first.stdout + first.stderr
    pieces = (results / "pieces.txt").read_text().splitlines()
    assert pieces[0] == killed + " killed"
    commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    words = pieces[1].split()
    assert words[:4] == ["piece", "1", "commit", commit] and words[-2:] == ["exit", "0"]
    assert int(words[words.index("seconds") + 1]) > 0 and int(words[words.index("peak_rss_mib") + 1]) > 100  # torch alone is more
    assert float(words[words.index("load_max") + 1]) >= float(words[words.index("load_mean") + 1]) > 0
    assert f" cpu {_processor()} seconds " in pieces[1] and [a.cpu for a in read_attempts(results)] == ["", _processor()]
    assert sorted(p.name for p in results.iterdir()) == ["checkpoints.txt", "config.yaml", "metrics.csv", "pieces.txt", "run.log", "summary.json"]
    sizes = [line.split("\t") for line in (results / "checkpoints.txt").read_text().splitlines()]
    assert sizes and all(int(size) > 1000 and name.startswith("checkpoints/checkpoint-") for size, name in sizes)
    assert (report / "results.md").exists() and (report / "es_vs_td3_Walker2d-v5.png").exists()
    assert not list(tmp_path.glob("run.piece*.alive"))
    second = call()
    assert second.returncode == 0
    assert (results / "pieces.txt").read_text().splitlines() == pieces  # finished: no new piece


def test_pause_runs_holds_a_run_and_lets_it_finish_with_its_pauses_recorded(tmp_path):
    """pause_runs.sh stops the named run's process (state T) without ending it; resumed, the run
    finishes, and paper_run.sh copies its pause record into the records."""
    import time

    run_dir, results = tmp_path / "run", tmp_path / "records"
    env = {**os.environ, "RESULTS": str(results), "REPORT": str(tmp_path / "report"), "PYTHON": sys.executable}
    runner = subprocess.Popen(["bash", str(ROOT / "scripts" / "paper_run.sh"), str(run_dir), "experiment=tiny", "td3.num_threads=1"],
                              cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    deadline = time.time() + 120
    while not (run_dir / ".hydra").exists() and time.time() < deadline:  # the recipe has started
        time.sleep(0.2)
    paused = _script("pause_runs.sh", "pause", str(run_dir))
    assert paused.returncode == 0 and paused.stdout.startswith("pause "), paused.stdout + paused.stderr
    pid = int(paused.stdout.split()[1])
    time.sleep(1)
    assert open(f"/proc/{pid}/stat").read().split(")")[1].split()[0] == "T"  # stopped, not gone
    resumed = _script("pause_runs.sh", "resume", str(run_dir))
    assert resumed.returncode == 0 and resumed.stdout.split()[:2] == ["resume", str(pid)]
    assert runner.wait(timeout=600) == 0, runner.stdout.read()
    lines = (results / "pauses.txt").read_text().splitlines()
    assert [line.split()[0] for line in lines] == ["pause", "resume"]
    assert _script("pause_runs.sh", "halt").returncode == 2


def test_tiny_digest_gives_the_same_digest_for_the_same_code_and_refuses_an_unknown_commit(tmp_path):
    """Two runs of one commit's tiny preset (named by its full and its short hash: two worktrees, two
    runs) give one digest of 64 hex digits, and the worktrees are gone afterwards; a commit that does
    not exist is refused by name."""
    git = lambda *args: subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    head, trees = git("rev-parse", "HEAD"), git("worktree", "list")
    done = _script("tiny_digest.sh", "es.py", head, head[:7], TMPDIR=str(tmp_path))
    assert done.returncode == 0, done.stdout + done.stderr
    lines = [line.split() for line in done.stdout.splitlines()]
    assert [line[0] for line in lines] == [head, head[:7]] and all(line[1:3] == ["2", "rows"] for line in lines)
    assert lines[0][3] == lines[1][3] and len(lines[0][3]) == 64 and int(lines[0][3], 16) >= 0
    assert git("worktree", "list") == trees and not list(tmp_path.iterdir())
    refused = _script("tiny_digest.sh", "es.py", "0000000", TMPDIR=str(tmp_path))
    assert refused.returncode == 2 and refused.stderr.strip() == "0000000: no such commit"


def test_arithmetic_record_digests_each_commit_once_and_keeps_a_block_it_has(tmp_path):
    """Two commits: the tiny preset's digest on each under a header naming them; a second call finds
    the block and runs nothing; one commit (named twice) writes no file."""
    git = lambda *args: subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    head, parent = git("rev-parse", "HEAD"), git("rev-parse", "--verify", "-q", "HEAD~1")
    if not parent:
        pytest.skip("no parent commit in this checkout")
    single = _script("arithmetic_record.sh", str(tmp_path), "es.py", "-", head, head[:7])
    assert single.returncode == 0 and not (tmp_path / "arithmetic.txt").exists()
    done = _script("arithmetic_record.sh", str(tmp_path), "es.py", "swimmer", parent, head, TMPDIR=str(tmp_path))
    assert done.returncode == 0, done.stdout + done.stderr
    header, *lines = (tmp_path / "arithmetic.txt").read_text().splitlines()
    assert header.startswith(f"# scripts/tiny_digest.sh es.py {parent[:7]} {head[:7]} (")
    assert [line.split()[:3] for line in lines] == [[parent[:7], "2", "rows"], [head[:7], "2", "rows"]]  # es.py takes no gradient steps: one block
    assert all(len(line.split()[3]) == 64 for line in lines)
    again = _script("arithmetic_record.sh", str(tmp_path), "es.py", "swimmer", parent, head, TMPDIR=str(tmp_path))
    assert again.returncode == 0 and (tmp_path / "arithmetic.txt").read_text().splitlines() == [header, *lines]
