"""``device=``: the recipes on every device this machine has (CPU, and CUDA where torch sees it), as
docs/running.md's "GPU" section and docs/deviations.md (34) say they run: TD3's side (actor,
critics, optimisers, buffers) on the device, the ES side on CPU. Tiny real runs in subprocesses:
where each part lives (read from the checkpoint), exact resume on the device, every learner and the
ERL and CEM-RL recipes, a run refused on another device than it was written on; and the same TD3
update on CPU and on the device. On a machine without CUDA these run on ``cpu``;
``scripts/device_check.sh`` runs them on a GPU machine."""
import json
import math
import signal
import subprocess

import pytest
import torch
from conftest import ROOT
from tensordict import TensorDict
from test_learners import built
from test_lifecycle import ENV, checkpoints, injected, one_line, rows_without_wall_time, run, tree

from benchmarks.common import transitions
from torchrl_esrl.collectors.td3_collector import make_frame_batches
from torchrl_esrl.modules.networks import make_actor, make_critic
from torchrl_esrl.objectives.td3 import TD3, ForeachSoftUpdate, ManualGradTD3Loss
from torchrl_esrl.run.checkpoint import checkpoint_paths
from torchrl_esrl.run.metrics import read_metrics

DEVICES = ["cpu", *(["cuda"] if torch.cuda.is_available() else [])]
OTHER = {"cpu": "cuda", "cuda": "cpu"}  # a device a run written on the key's is resumed on (refused)


def tensor_devices(run_dir, component: str) -> dict[str, str]:
    """``{path in the state dict: device}`` of every tensor the newest checkpoint of ``run_dir``
    saved for ``component`` (TorchRL's state-dict files record each tensor's device)."""
    folder = next((checkpoint_paths(run_dir)[0] / "components").glob(f"*-{component}"))

    def walk(node, path):
        if isinstance(node, dict):
            if node.get("kind") == "tensor":
                yield "/".join(path), node["device"]
            elif node.get("kind") != "value":
                for item in node.get("items", []):
                    key, value = item if isinstance(item, list) and len(item) == 2 else (None, item)
                    name = key.get("value") if isinstance(key, dict) else key
                    yield from walk(value, path if name is None else (*path, str(name)))
        elif isinstance(node, list):
            for index, value in enumerate(node):
                yield from walk(value, (*path, str(index)))

    return dict(walk(json.loads((folder / "state.json").read_text()), ()))


def assert_learner_and_buffers_on(run_dir, device: str, learner: str) -> None:
    """The learner's networks and Adam moments and the buffers' storages were on ``device``."""
    saved = tensor_devices(run_dir, learner)
    networks = {path: on for path, on in saved.items() if "network_params" in path or "exp_avg" in path}
    storages = {path: on for path, on in tensor_devices(run_dir, "buffer").items() if "/_storage/" in path}
    assert networks and storages
    assert {torch.device(on).type for on in (*networks.values(), *storages.values())} == {device}, (networks, storages)


def assert_finite_rows(run_dir, iterations: int = 2) -> list[dict]:
    rows = read_metrics(run_dir / "metrics.csv")
    assert len(rows) == iterations
    for row in rows:
        for key, value in row.items():
            assert not isinstance(value, float) or math.isfinite(value), (key, row)
    return rows


@pytest.mark.e2e
@pytest.mark.parametrize("device", DEVICES)
def test_es_td3_trains_on_the_device_and_a_killed_run_resumes_to_the_same_records(tmp_path, device):
    """ES-TD3Buffers with ``device``: TD3 and the buffers there, the ES mean on CPU, the CUDA
    generator checkpointed on CUDA; killed at its first checkpoint (mid-episode) and rerun, it
    writes the uninterrupted run's rows."""
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    result = run(whole, f"device={device}")
    assert result.returncode == 0, result.stderr[-3000:]
    assert_finite_rows(whole)
    assert_learner_and_buffers_on(whole, device, "td3")
    assert set(tensor_devices(whole, "es").values()) == {"cpu"}  # the ES mean and its generator
    assert any(path.startswith("torch_cuda") for path in tensor_devices(whole, "rng")) == (device == "cuda")
    summary = json.loads((whole / "summary.json").read_text())
    assert math.isfinite(summary["final_return"]) and summary["td3_updates"] > 0
    stopped = subprocess.run([*injected("inject_kill.py", "first_checkpoint", "es_td3.py", killed), f"device={device}"], cwd=ROOT, capture_output=True, text=True, timeout=900, env=ENV)
    assert stopped.returncode == -signal.SIGKILL, stopped.stderr[-3000:]
    assert len(checkpoints(killed)) == 1 and not rows_without_wall_time(killed)
    resumed = run(killed, f"device={device}")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert rows_without_wall_time(killed) == rows_without_wall_time(whole)


@pytest.mark.e2e
@pytest.mark.parametrize("written", DEVICES)
def test_a_run_rerun_on_another_device_is_refused_in_one_line_and_finishes_on_its_own(tmp_path, written):
    """A checkpoint holds its device's tensors and random streams: the same command with another
    ``device`` (CUDA here, or a machine without it) is refused in one line naming ``device``, exit 2,
    the run directory byte for byte as it was; the run's own device then finishes it."""
    stopped = subprocess.run([*injected("inject_kill.py", "first_checkpoint", "es_td3.py", tmp_path), f"device={written}"], cwd=ROOT, capture_output=True, text=True, timeout=900, env=ENV)
    assert stopped.returncode == -signal.SIGKILL, stopped.stderr[-3000:]
    before = tree(tmp_path)
    refused = run(tmp_path, f"device={OTHER[written]}")
    line = one_line(refused)
    assert refused.returncode == 2 and line.startswith("config error: device: "), refused.stderr[-3000:]
    assert tree(tmp_path) == before
    finished = run(tmp_path, f"device={written}")
    assert finished.returncode == 0, finished.stderr[-3000:]
    assert_finite_rows(tmp_path)


@pytest.mark.e2e
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("script, extra, learner", [
    ("es_td3.py", ("learner=ddpg",), "td3"),
    ("es_td3.py", ("learner=sac",), "td3"),
    ("erl.py", (), "learner"),  # DDPG, ERL's learner
    ("cem_rl.py", (), "td3"),
])
def test_every_learner_and_the_erl_and_cem_rl_recipes_train_on_the_device(tmp_path, device, script, extra, learner):
    result = run(tmp_path, *extra, f"device={device}", script=script)
    assert result.returncode == 0, result.stderr[-3000:]
    assert_finite_rows(tmp_path)
    assert_learner_and_buffers_on(tmp_path, device, learner)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("learner", ["td3", "ddpg", "sac"])
def test_the_collector_steps_the_learners_own_exploration_policy_on_the_device(device, learner):
    """Every tensor of the behaviour policy (its random warm-up's too) is on the learner's device, so
    TorchRL's ``Collector`` steps that policy itself, not a copy made when it was built (which a
    restore, the warm-up's counter and its reset would not reach)."""
    cfg, env, learned = built(learner, 0, f"device={device}", "td3.random_frames=10", "implementation=reference")
    policy = learned.exploration_policy
    assert {t.device.type for t in TensorDict.from_module(policy).values(True, True)} == {device}
    collector, _ = make_frame_batches(cfg, env, learned)
    try:
        assert collector.policy is policy
    finally:
        collector.shutdown()


def test_resume_option_refuses_a_run_written_on_a_device_this_machine_lacks(tmp_path):
    from torchrl_esrl.errors import ConfigError
    from torchrl_esrl.run.resume import check_saved_device

    for device in DEVICES:
        check_saved_device(tmp_path, device)
    with pytest.raises(ConfigError, match=r"^device: .* was written with device=cuda:99, which this machine lacks"):
        check_saved_device(tmp_path, "cuda:99")


# ------------------------------------------------------------------ one TD3 update, CPU and device
TD3_PIECES = {
    "fast": {"loss_class": ManualGradTD3Loss, "target_update_class": ForeachSoftUpdate, "optimizer_impl": "fused"},  # make_td3's
    "reference": {},  # TorchRL's TD3Loss, SoftUpdate, torch's Adam
}
# float32 on both; sums in another order round differently: relative 1e-5 on losses, gradients and
# parameters. Adam's first step moves a parameter by lr * g / (|g| + eps), its sign where the gradient
# g is tiny, which that rounding can flip: parameters whose gradient is under 1e-4 of the largest are
# compared by their gradient and by the step's bound (2 lr) only.
RTOL, ATOL = 1e-5, 1e-6
TINY_GRADIENT = 1e-4
LR = 3e-4


def one_update(device: str, pieces: str):
    """TD3 (paper sizes, HalfCheetah's dimensions, policy delay 1: critic, actor and targets in one
    update) from fixed initial weights, after one update on a fixed batch with some terminations; no
    target smoothing noise (the devices' generators draw different numbers)."""
    from torchrl.data import Bounded

    spec = Bounded(-torch.ones(6), torch.ones(6), shape=(6,))
    torch.manual_seed(0)
    actor, critic = make_actor(17, spec), make_critic(17, 6)
    built = TD3(actor, critic, spec, lr=LR, policy_delay=1, policy_noise=0.0)  # the initial weights, on CPU
    td3 = TD3(make_actor(17, spec).to(device), make_critic(17, 6).to(device), spec.to(device), lr=LR, policy_delay=1, policy_noise=0.0, **TD3_PIECES[pieces])
    td3.loss.load_state_dict(built.loss.state_dict())  # the networks and targets (not the optimisers: their options are the pieces')
    batch = transitions(256, 17, 6, torch.Generator().manual_seed(0))
    batch["next", "terminated"][::9] = True
    out = td3.update(batch.to(device))
    named = {name: (p.detach().cpu(), p.grad.detach().cpu()) for name, p in td3.loss.named_parameters()}
    targets = {name: t.cpu() for name, t in (*td3.loss.target_actor_network_params.items(True, True), *td3.loss.target_qvalue_network_params.items(True, True))}
    return out, named, targets


@pytest.mark.parametrize("device, pieces", [(d, p) for d in DEVICES for p in TD3_PIECES if (d, p) != ("cpu", "reference")])
def test_one_td3_update_on_the_device_equals_the_cpu_reference(device, pieces):
    """The same TD3 update (same batch, same initial weights) with ``pieces`` on ``device`` and with
    TorchRL's reference pieces on CPU: losses, gradients, parameters and targets equal to float32
    rounding (:data:`RTOL`, :data:`ATOL`, :data:`TINY_GRADIENT`)."""
    out, named, targets = one_update(device, pieces)
    expected_out, expected, expected_targets = one_update("cpu", "reference")
    assert out.keys() == expected_out.keys() == {"critic_loss", "actor_loss"}
    for key in out:
        assert out[key] == pytest.approx(expected_out[key], rel=RTOL), key
    assert named.keys() == expected.keys()
    for name, (parameter, gradient) in named.items():
        expected_parameter, expected_gradient = expected[name]
        scale = expected_gradient.abs().max()
        torch.testing.assert_close(gradient, expected_gradient, rtol=100 * RTOL, atol=RTOL * scale.item(), msg=name)
        clear = expected_gradient.abs() > TINY_GRADIENT * scale
        torch.testing.assert_close(parameter[clear], expected_parameter[clear], rtol=RTOL, atol=ATOL, msg=name)
        assert (parameter - expected_parameter).abs().max() <= 2 * LR + ATOL, name
    assert targets.keys() == expected_targets.keys()
    for name, target in targets.items():
        torch.testing.assert_close(target, expected_targets[name], rtol=RTOL, atol=ATOL, msg=str(name))
