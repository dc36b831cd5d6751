"""The README's first command (``experiment=demo``), shortened, in a real subprocess: the returned
ES mean solves InvertedPendulum-v5, the console is quiet, one line per iteration when it is not a
terminal, and its last lines say the returns and where the files and the plot are."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

from torchrl_esrl.run.metrics import read_metrics

ROOT = Path(__file__).resolve().parents[1]
TOP = 1000.0  # InvertedPendulum-v5: the pole stays up for all 1000 steps


@pytest.mark.e2e
def test_demo_shortened_solves_the_task_and_says_so_quietly(tmp_path):
    # 10 of the preset's 15 iterations (seed 0); everything else is the preset.
    result = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "es_td3.py"), "experiment=demo", "iterations=10", f"hydra.run.dir={tmp_path}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=900,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    rows = read_metrics(tmp_path / "metrics.csv")

    # The returned policy solves the task from an initial policy that does not, on the same protocol.
    assert summary["final_episodes"] == 5 and summary["initial_return"] < 0.1 * TOP
    assert summary["final_return"] >= 0.9 * TOP, summary
    # The TD3 actor got there and the overwrite rule handed it to the ES mean.
    assert summary["overwrites"] >= 1 and max(r["td3_eval_return"] for r in rows) >= 0.9 * TOP
    assert rows[-1]["es_eval_return"] >= 0.9 * TOP

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
    # Not a terminal: the line naming each piece's implementation, one plain line per iteration,
    # then at most 8 lines of results, no bar.
    lines = result.stdout.strip().splitlines()
    assert lines[0].startswith("pieces: td3_loss fast, ") and lines[0].endswith("es_physics reference (env.id: InvertedPendulum-v5 is not a task it knows (HalfCheetah-v5, Swimmer-v5, Walker2d-v5, Hopper-v5, Ant-v5))"), lines[0]
    assert lines[0].count("reference") == 1  # every other piece runs fast on the demo's task
    assert [line.split(" | ")[0] for line in lines[1:11]] == [f"iteration {i}/10" for i in range(1, 11)]
    assert len(lines) <= 1 + 10 + 8 and "\r" not in console


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
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    from torchrl_esrl.envs import quiet_logs

    class Records(logging.Handler):  # what reaches TorchRL's handlers (its console handler holds the stdout of import time)
        def __init__(self):
            super().__init__()
            self.messages = []

        def emit(self, record):
            self.messages.append(record.getMessage())

    records = Records()
    torchrl_logger = logging.getLogger("torchrl")  # TorchRL's own logger, by its public name
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
