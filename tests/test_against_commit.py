"""benchmarks.against_commit: a past commit's package imported beside the working tree's, both TD3 updates timed.

Run as its own process, as its usage says: the base package it imports registers its own Hydra schemas."""
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_a_past_commits_td3_update_is_timed_beside_the_working_trees(tmp_path):
    out = tmp_path / "against.json"
    command = [sys.executable, "-m", "benchmarks.against_commit", "--base", "HEAD~1", "--rounds", "2", "--calls", "2", "--capacity", "300", "--out", str(out)]
    result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads(out.read_text())
    base = subprocess.run(["git", "rev-parse", "HEAD~1"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
    assert report["base"] == base and set(report["rounds_ms"]) == {"base", "now"}
    assert all(len(values) == 2 and min(values) > 0 for values in report["rounds_ms"].values())
    ratio = report["ratio_now_over_base"]
    assert ratio["q1"] <= ratio["median"] <= ratio["q3"]
    assert "now/base" in result.stdout
