"""benchmarks.against_commit: a past commit's package imported beside the working tree's, both TD3 updates timed."""
import sys

from benchmarks import against_commit


def test_a_past_commits_td3_update_is_timed_beside_the_working_trees(tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "path", list(sys.path))
    report = against_commit.run("HEAD~1", rounds=2, calls=2, capacity=300)
    base = sys.modules[f"{against_commit.BASE_PACKAGE}.objectives.td3"]
    assert base.TD3 is not sys.modules["torchrl_esrl.objectives.td3"].TD3
    assert base.ManualGradTD3Loss.__module__.startswith(against_commit.BASE_PACKAGE)  # its own imports point at the base package
    assert len(report["base"]) == 40 and set(report["rounds_ms"]) == {"base", "now"}
    assert all(len(values) == 2 and min(values) > 0 for values in report["rounds_ms"].values())
    assert report["ratio_now_over_base"]["q1"] <= report["ratio_now_over_base"]["median"] <= report["ratio_now_over_base"]["q3"]
