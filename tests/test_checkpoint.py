"""A checkpoint proves it is whole (torchrl_esrl/run/checkpoint.py): the digests recorded when it
is written are checked when it is read, so damage that keeps every size and every JSON file
valid is found, and a restore falls back to the previous checkpoint; a save that would not fit
stops before writing. Real TorchRL checkpoints of real modules and replay buffers; the recipes'
use is in tests/test_lifecycle.py."""
import json
import random
import shutil

import pytest
import torch
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from tensordict import TensorDict

from torchrl_esrl.errors import CheckpointWriteError
from torchrl_esrl.run.checkpoint import DIGESTS, RunCheckpoint, checkpoint_paths, unreadable
from torchrl_esrl.run.progress import RunProgress


def make(run_dir, expected_bytes=0, seed=0):
    torch.manual_seed(seed)
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(500), batch_size=8)
    buffer.extend(TensorDict({"obs": torch.randn(300, 17), "action": torch.rand(300, 6)}, batch_size=[300]))
    parts = {"progress": RunProgress(), "actor": torch.nn.Linear(17, 6), "buffer": buffer}
    return RunCheckpoint(run_dir, {"seed": seed}, every_frames=0, keep_last=2, algorithm="test", expected_bytes=expected_bytes, **parts), parts


def two_checkpoints(run_dir):
    checkpoint, parts = make(run_dir)
    checkpoint.save()
    parts["progress"].iteration = 1
    with torch.no_grad():
        parts["actor"].weight.add_(1.0)
    checkpoint.save()
    previous, newest = checkpoint_paths(run_dir)[1], checkpoint_paths(run_dir)[0]
    return previous, newest


def largest_tensor_file(checkpoint):
    return max(checkpoint.rglob("*.memmap"), key=lambda p: p.stat().st_size)


def overwrite_same_length(path, seed=0):
    path.write_bytes(random.Random(seed).randbytes(path.stat().st_size))


def test_every_file_of_a_checkpoint_has_its_digest_and_a_whole_one_passes(tmp_path):
    previous, newest = two_checkpoints(tmp_path)
    record = json.loads(next(newest.glob(f"components/*-{DIGESTS}/digests.json")).read_text())
    manifest = json.loads((newest / "manifest.json").read_text())
    listed = {f"{r['path']}/{f}" for name, r in manifest["components"].items() if name != DIGESTS for f in r["files"]}
    assert record["hash"] == "sha256" and set(record["files"]) == listed and any(f.endswith(".memmap") for f in listed)
    assert unreadable(newest) is None and unreadable(previous) is None


@pytest.mark.parametrize("how", ["tensor_garbage", "one_bit", "json_rewritten", "metadata_changed", "digests_garbage"])
def test_same_size_damage_is_found_and_the_restore_falls_back(tmp_path, capsys, how):
    previous, newest = two_checkpoints(tmp_path)
    if how == "tensor_garbage":  # same length, so the size check cannot see it
        overwrite_same_length(largest_tensor_file(newest))
    elif how == "one_bit":
        path = largest_tensor_file(newest)
        data = bytearray(path.read_bytes())
        data[len(data) // 2] ^= 1
        path.write_bytes(bytes(data))
    elif how == "json_rewritten":  # still valid JSON, another value
        path = next(newest.glob("components/*-progress/state.json"))
        text = path.read_text()
        changed = text.replace('"iteration"},{"kind":"value","value":1}', '"iteration"},{"kind":"value","value":7}')
        assert changed != text
        path.write_text(changed)
    elif how == "metadata_changed":  # the manifest still parses and validates
        manifest = json.loads((newest / "manifest.json").read_text())
        manifest["metadata"]["iteration"] = 7
        (newest / "manifest.json").write_text(json.dumps(manifest))
    else:
        overwrite_same_length(next(newest.glob(f"components/*-{DIGESTS}/digests.json")))
    reason = unreadable(newest)
    assert reason is not None and ("digest" in reason), reason
    checkpoint, parts = make(tmp_path)
    assert checkpoint.restore() == previous
    assert parts["progress"].iteration == 0  # the previous checkpoint's state
    said = capsys.readouterr().err.strip().splitlines()
    assert len(said) == 1 and newest.name in said[0] and said[0].endswith(f"resuming from {previous.name}")


def test_a_checkpoint_without_digests_still_restores(tmp_path):
    """Checkpoints written before digests were recorded are checked as before."""
    _, newest = two_checkpoints(tmp_path)
    manifest = json.loads((newest / "manifest.json").read_text())
    shutil.rmtree(newest / manifest["components"].pop(DIGESTS)["path"])
    (newest / "manifest.json").write_text(json.dumps(manifest))
    assert unreadable(newest) is None
    checkpoint, parts = make(tmp_path)
    assert checkpoint.restore() == newest and parts["progress"].iteration == 1


def test_a_save_that_would_not_fit_stops_before_writing(tmp_path):
    checkpoint, _ = make(tmp_path)
    kept = checkpoint.save()
    free = shutil.disk_usage(tmp_path).free
    full, _ = make(tmp_path, expected_bytes=free + 2**30)
    with pytest.raises(CheckpointWriteError) as error:
        full.save()
    message = str(error.value)
    assert "No space left on device" in message and f"last good checkpoint kept: {kept.name}" in message and "\n" not in message
    assert checkpoint_paths(tmp_path) == [kept] and not list((tmp_path / "checkpoints").glob(".*"))
