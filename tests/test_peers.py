"""benchmarks.peers: the three implementations it times compute TD3 with the same values and network sizes,
and each of them learns in the frames it times."""
import json
import math

import pytest

from benchmarks import peers

IMPLEMENTATIONS = ("ours", "cleanrl_style", "torchrl_stock")


def test_a_few_frames_of_each_implementation_learn_with_the_same_td3(tmp_path):
    out = tmp_path / "peers.json"
    peers.main(["--quick", "--envs", "Walker2d-v5", "--frames", "3", "--repeats", "1", "--prefill", "256", "--out", str(out)])
    report = json.loads(out.read_text())
    r = report["envs"]["Walker2d-v5"]
    threads = r["methods"]["cleanrl_style"]["torch_threads"]  # the job's cores, whatever torch was left at
    assert threads == r["methods"]["torchrl_stock"]["torch_threads"] == r["methods"]["ours"]["torch_threads"]
    assert set(r["methods"]) == {*IMPLEMENTATIONS, "plain_update_1thread", *([f"plain_update_{threads}threads"] if threads > 1 else [])}
    for name, method in r["methods"].items():
        assert method["ms_per_frame"] > 0 and len(method["rounds_ms_per_frame"]) == 1 and method["torch_threads"] >= 1
        if name != "ours":
            assert r[f"speedup_vs_{name}"] == pytest.approx(method["ms_per_frame"] / r["methods"]["ours"]["ms_per_frame"])
    assert r["best_peer"] in ("cleanrl_style", "torchrl_stock") and r["best_plain_update"].startswith("plain_update_")
    for name in IMPLEMENTATIONS:
        assert math.isfinite(r["critic_loss"][name]), name
        assert r["parameters_moved"][name] == {"actor": True, "critics": True}, name
        assert r["parameter_count"][name] == r["parameter_count"]["ours"], name  # 17-256-256-6 actor, two 23-256-256-1 critics
        assert r["hyperparameters"][name] == pytest.approx(r["hyperparameters"]["ours"]), name
    assert r["parameter_count"]["ours"] == {"actor": 17 * 256 + 256 + 256 * 256 + 256 + 256 * 6 + 6, "critics": 2 * (23 * 256 + 256 + 256 * 256 + 256 + 256 + 1)}
    assert r["hyperparameters"]["ours"] == pytest.approx({"gamma": 0.99, "tau": 0.005, "policy_noise": 0.2, "noise_clip": 0.5, "actor_lr": 3e-4, "critic_lr": 3e-4,
                                                           "policy_delay": 2, "exploration_noise": 0.1, "batch_size": 256})
    assert set(report["load_average_1min"]) == {"start", "end"} and "model_name" in report["machine"]["cpu"]


@pytest.mark.parametrize("argv", [["--prefill", "100"], ["--frames", "0"], ["--envs", "Pong-v5"]])
def test_bad_input_exits_2_naming_the_option(argv, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit:
        peers.main([*argv, "--out", str(tmp_path / "peers.json")])
    assert exit.value.code == 2 and argv[0] in capsys.readouterr().err
    assert not (tmp_path / "peers.json").exists()
