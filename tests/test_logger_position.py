"""The logger's position in a checkpoint (torchrl_esrl/run/logger_position.py), through real
TorchRL checkpoints of a run directory: rows written after a checkpoint are dropped on restore,
rows cut or garbled before it are written back from the checkpoint's copy, and a checkpoint that
keeps no copy (written before checkpoints kept one) refuses a file that lacks its rows. The
recipes' use is in tests/test_lifecycle.py."""
import pytest
import torch

from torchrl_esrl.errors import ConfigError
from torchrl_esrl.run.checkpoint import RunCheckpoint
from torchrl_esrl.run.logger_position import LoggerPosition, MetricsDamaged
from torchrl_esrl.run.metrics import MetricsLog, read_metrics
from torchrl_esrl.run.progress import RunProgress


def logged_run(run_dir, rows=2):
    """A run directory with ``rows`` rows of metrics.csv and of the csv logger, checkpointed after them."""
    log = MetricsLog(run_dir, backend="csv", experiment_name="test")
    progress = RunProgress()
    checkpoint = RunCheckpoint(run_dir, {}, every_frames=0, keep_last=2, progress=progress, actor=torch.nn.Linear(3, 2))
    for iteration in range(rows):
        log.log({"iteration": iteration, "td3_frames": 100 * (iteration + 1), "eval_return": -1.25 * iteration})
        progress.finish_iteration()
        checkpoint.save()
    return log, checkpoint


def restored(run_dir):
    return RunCheckpoint(run_dir, {}, every_frames=0, keep_last=2, progress=RunProgress(), actor=torch.nn.Linear(3, 2))


def files(run_dir):
    return {str(p.relative_to(run_dir)): p.read_bytes() for p in sorted(run_dir.rglob("*.csv"))}


@pytest.mark.parametrize("damage", ["cut_mid_row", "zeroed", "removed", "logger_file_cut"])
def test_rows_damaged_before_the_checkpoint_are_written_back_from_its_copy(tmp_path, capsys, damage):
    log, _ = logged_run(tmp_path)
    whole = files(tmp_path)
    metrics = tmp_path / "metrics.csv"
    logger_file = next(p for p in (tmp_path / "logs").rglob("eval_return.csv"))
    if damage == "cut_mid_row":
        metrics.write_bytes(metrics.read_bytes()[:-9])
    elif damage == "zeroed":
        data = bytearray(metrics.read_bytes())
        data[10:30] = bytes(20)
        metrics.write_bytes(bytes(data))
    elif damage == "removed":
        metrics.unlink()
    else:
        logger_file.write_bytes(logger_file.read_bytes()[:-3])
    checkpoint = restored(tmp_path)
    assert checkpoint.restore() is not None
    assert files(tmp_path) == whole
    said = capsys.readouterr().err.strip().splitlines()
    damaged = str(logger_file.relative_to(tmp_path)) if damage == "logger_file_cut" else "metrics.csv"
    assert len(said) == 1 and said[0].startswith(f"{damaged} in {tmp_path} did not begin with the rows") and "written back from its copy" in said[0], said
    assert [row["iteration"] for row in read_metrics(metrics)] == [0, 1]


def test_rows_written_after_the_checkpoint_are_dropped_without_a_word(tmp_path, capsys):
    log, _ = logged_run(tmp_path)
    whole = files(tmp_path)
    with (tmp_path / "metrics.csv").open("ab") as handle:
        handle.write(b"2,300,-2.")  # a row the kill cut, after the last checkpoint
    assert restored(tmp_path).restore() is not None
    assert files(tmp_path) == whole and capsys.readouterr().err == ""


def test_a_checkpoint_without_a_copy_refuses_a_file_that_lacks_its_rows(tmp_path):
    """A checkpoint written before checkpoints kept a copy knows only the file's size: a file
    shorter than it, or garbled before it, cannot be continued from it."""
    logged_run(tmp_path, rows=1)
    path = tmp_path / "metrics.csv"
    size = path.stat().st_size
    position = LoggerPosition(tmp_path)
    path.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(MetricsDamaged, match=f"^{path} holds {size - 5} bytes, this checkpoint counts {size}: rows written before it are lost"):
        position.load_state_dict({"files": {"metrics.csv": size}})
    path.write_bytes(path.read_bytes()[:-2] + b"\0\0\0\0\0\0\0\r\n")
    with pytest.raises(MetricsDamaged, match="is damaged \\(line 2 holds a NUL byte\\)"):
        position.load_state_dict({"files": {"metrics.csv": size}})


def test_with_every_checkpoint_unable_to_continue_the_file_the_restore_is_one_line_naming_it(tmp_path):
    _, checkpoint = logged_run(tmp_path)
    keep = checkpoint.logger_position.state_dict
    checkpoint.logger_position.state_dict = lambda: {"files": keep()["files"]}  # as checkpoints without a copy were written
    checkpoint.progress.finish_iteration()
    checkpoint.save()
    checkpoint.progress.finish_iteration()
    checkpoint.save()
    (tmp_path / "metrics.csv").write_bytes(b"iteration,td3")
    with pytest.raises(ConfigError) as error:
        restored(tmp_path).restore()
    line = str(error.value)
    assert "\n" not in line and f"logger: {tmp_path / 'metrics.csv'} holds 13 bytes" in line and line.startswith("no checkpoint in"), line
