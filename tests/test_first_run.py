"""The README's first command (``experiment=demo``), shortened, in a real subprocess: the returned
ES mean beats the initial policy, the ES mean took part, the console is quiet and its last lines
say the returns and where the files and the plot are."""
import json
import subprocess
import sys
from itertools import pairwise
from pathlib import Path

import pytest

from torchrl_esrl.run.metrics import read_metrics

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.e2e
def test_demo_shortened_learns_and_says_so_quietly(tmp_path):
    # 2 of the preset's 8 iterations; everything else is the preset (InvertedPendulum-v5).
    result = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "es_td3.py"), "experiment=demo", "iterations=2", f"hydra.run.dir={tmp_path}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=900,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    rows = read_metrics(tmp_path / "metrics.csv")

    # The returned policy is clearly better than the initial one, on the same protocol.
    assert summary["final_episodes"] == 5 and summary["initial_return"] is not None
    assert summary["final_return"] >= 2 * summary["initial_return"] + 5, summary
    # The ES mean took part: it was overwritten, or it improved by itself between iterations.
    es_improved = any(b["es_eval_return"] > a["es_eval_return"] and not a["overwritten"] for a, b in pairwise(rows))
    assert summary["overwrites"] >= 1 or es_improved

    # The last lines: returns of the returned policy, the TD3 actor and the initial policy, and where things are.
    out = result.stdout
    assert "returned policy (ES mean)" in out and f"{summary['final_return']:.1f}" in out
    assert "TD3 actor" in out and f"{summary['final_td3_actor_return']:.1f}" in out
    assert "initial policy" in out and f"{summary['initial_return']:.1f}" in out
    assert str(tmp_path) in out and str(tmp_path / "learning_curve.png") in out
    png = (tmp_path / "learning_curve.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000

    # Quiet: no config dump, no MuJoCo deprecation (on the console or in MUJOCO_LOG.TXT), no storage INFO.
    console = result.stdout + result.stderr
    assert "settotalmass" not in console and not (tmp_path / "MUJOCO_LOG.TXT").exists()
    assert "Initialized LazyTensorStorage" not in console
    assert "frames_per_iteration:" not in console and "population_size:" not in console
    assert (tmp_path / ".hydra" / "config.yaml").exists()  # the config is in the run directory instead
    assert len(result.stdout.strip().splitlines()) <= 8


@pytest.mark.e2e
def test_print_config_shows_the_resolved_config(tmp_path):
    result = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "es.py"), "experiment=demo", "iterations=1", "es.generations_per_iteration=1",
         "logger.print_config=true", "logger.progress=false", f"hydra.run.dir={tmp_path}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=600,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "population_size: 10" in result.stdout and "id: InvertedPendulum-v5" in result.stdout


def test_quiet_logs_silences_exactly_the_two_messages(tmp_path, monkeypatch, capfd):
    import logging

    import gymnasium as gym
    import torch
    from tensordict import TensorDict
    from torchrl._utils import logger as torchrl_logger
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    from torchrl_esrl.envs import quiet_logs

    class Records(logging.Handler):  # what reaches TorchRL's handlers (its console handler holds the stdout of import time)
        def __init__(self):
            super().__init__()
            self.messages = []

        def emit(self, record):
            self.messages.append(record.getMessage())

    records = Records()
    torchrl_logger.addHandler(records)
    monkeypatch.chdir(tmp_path)
    quiet_logs()
    env = gym.make("HalfCheetah-v5")  # its model compile warns about 'settotalmass'
    env.reset(seed=0)
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(10))
    buffer.extend(TensorDict({"x": torch.zeros(4, 2)}, batch_size=[4]))  # TorchRL logs the storage's shape at INFO
    torchrl_logger.info("another TorchRL message")
    torchrl_logger.removeHandler(records)
    captured = capfd.readouterr()
    assert "settotalmass" not in captured.out + captured.err and not (tmp_path / "MUJOCO_LOG.TXT").exists()
    assert not any("Initialized LazyTensorStorage" in m for m in records.messages)
    assert "another TorchRL message" in records.messages  # other messages still come through
