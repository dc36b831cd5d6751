"""One writer per run directory (torchrl_esrl/run/lock.py): a live holder keeps a second writer
out with a line naming it, a dead one (SIGKILL) does not, and a refusal changes nothing. The
recipes' use of it is in tests/test_lifecycle.py."""
import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import ROOT, recipe_command

from torchrl_esrl.errors import ConfigError
from torchrl_esrl.run.lock import LOCK_NAME, RunLock, holder

HOLD = "import sys, time; from torchrl_esrl.run.lock import RunLock; RunLock(sys.argv[1]).acquire(); print('held', flush=True); time.sleep(600)"
ENV = {**os.environ, "MUJOCO_QUIET": "1", "OMP_NUM_THREADS": "1"}


def tree(directory):
    return {str(p.relative_to(directory)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(Path(directory).rglob("*")) if p.is_file()}


@pytest.fixture
def held(tmp_path):
    """``held(run_dir)``: another process holding ``run_dir``'s lock (killed at the end)."""
    processes = []

    def hold(run_dir):
        process = subprocess.Popen([sys.executable, "-c", HOLD, str(run_dir)], cwd=ROOT, stdout=subprocess.PIPE, text=True, env=ENV)
        assert process.stdout.readline().strip() == "held"
        processes.append(process)
        return process

    yield hold
    for process in processes:
        process.kill()
        process.wait()


def test_a_live_holder_keeps_a_second_writer_out_and_a_killed_one_does_not(tmp_path, held):
    run_dir = tmp_path / "run"
    process = held(run_dir)
    record = holder(run_dir)
    assert record["pid"] == process.pid and record["host"] == socket.gethostname()
    before = tree(run_dir)
    with pytest.raises(ConfigError) as error:
        RunLock(run_dir).acquire()
    message = str(error.value)
    assert message.startswith(f"hydra.run.dir: {run_dir} is being written by another run (pid {process.pid} on {socket.gethostname()}, since ")
    assert record["since"] in message and "nothing was changed" in message and "allowed" in message and "\n" not in message
    assert tree(run_dir) == before  # the refusal wrote nothing, not even its own record
    process.send_signal(signal.SIGKILL)
    process.wait()
    lock = RunLock(run_dir).acquire()  # the kernel released the dead holder's lock
    try:
        assert holder(run_dir)["pid"] == os.getpid()
    finally:
        lock.release()


def test_a_released_lock_can_be_taken_again_in_the_same_process(tmp_path):
    first = RunLock(tmp_path).acquire()
    first.release()
    second = RunLock(tmp_path).acquire()
    second.release()
    assert (tmp_path / LOCK_NAME).exists() and json.loads((tmp_path / LOCK_NAME).read_text())["pid"] == os.getpid()


@pytest.mark.e2e
@pytest.mark.parametrize("multirun", [False, True], ids=["single", "multirun"])
def test_a_recipe_refuses_a_run_directory_another_process_writes(tmp_path, held, multirun):
    run_dir = tmp_path / ("sweep/0" if multirun else "run")
    process = held(run_dir)
    before = tree(run_dir)
    where = ["-m", f"hydra.sweep.dir={tmp_path / 'sweep'}"] if multirun else [f"hydra.run.dir={run_dir}"]
    result = subprocess.run(recipe_command("es_td3.py", *where), cwd=ROOT, capture_output=True, text=True, timeout=300, env=ENV)
    lines = [line for line in result.stderr.strip().splitlines() if "being written" in line or "error" in line.lower()]
    assert result.returncode == 2 and len(lines) == 1, result.stderr[-3000:]
    assert lines[0].startswith(f"config error: hydra.run.dir: {run_dir} is being written by another run (pid {process.pid} on "), lines[0]
    if multirun:
        # Hydra writes a job's .hydra/ files and opens its log before any callback of the job runs
        after = {k: v for k, v in tree(run_dir).items() if not k.startswith(".hydra/")}
        assert after.pop("es_td3.log") == hashlib.sha256(b"").hexdigest() and after == before
    else:
        assert tree(run_dir) == before and not result.stdout.strip()  # not even Hydra's .hydra/ files
