"""The Hydra recipe end to end, in a real subprocess, on real MuJoCo with a tiny budget."""
import json

import pytest

from torchrl_esrl.run.metrics import CORE_COLUMNS, read_metrics

pytestmark = pytest.mark.e2e

# What ES-TD3Buffers reports besides the core columns (each from the component it describes).
ES_TD3_COLUMNS = (
    "td3_updates", "td3_eval_return", "es_eval_return", "td3_average", "es_average", "overwritten", "best_return", "threshold",
    "good_size", "bad_size", "noisy_size", "es_generation_mean_return", "es_generation_max_return", "critic_loss", "actor_loss", "buffer_mode",
)


def test_tiny_preset_writes_every_output(run_recipe, tmp_path):
    result = run_recipe("es_td3.py", "env=halfcheetah", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    rows = read_metrics(tmp_path / "metrics.csv")
    assert len(rows) == 2
    assert tuple(rows[0]) == (*CORE_COLUMNS, *ES_TD3_COLUMNS)
    assert [r["iteration"] for r in rows] == [0, 1]
    assert [r["td3_frames"] for r in rows] == [400, 800]
    assert rows[-1]["es_frames"] > rows[0]["es_frames"] > 0
    assert rows[-1]["good_size"] + rows[-1]["bad_size"] == rows[-1]["es_frames"]  # every ES step routed
    assert rows[-1]["noisy_size"] == 800
    # renormalised readiness: noisy holds K=256 after 300 frames (batches of 50), then one update per frame
    assert [r["td3_updates"] for r in rows] == [150, 550]
    assert rows[-1]["threshold"] <= rows[-1]["best_return"]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["env"] == "HalfCheetah-v5" and summary["ratio"] == [0.5, 0.2, 0.3]
    for key in ("final_es_mean_return", "final_td3_actor_return", "td3_frames", "es_frames", "wall_time_s"):
        assert key in summary
    assert (tmp_path / "es_mean.pt").exists() and (tmp_path / "td3_actor.pt").exists()
    scalars = list((tmp_path / "logs").rglob("td3_eval_return.csv"))
    assert scalars and scalars[0].read_text().strip()  # TorchRL's csv logger got the values


def test_multirun_sweeps_the_ratio_one_directory_per_ratio(run_recipe, tmp_path):
    result = run_recipe("es_td3.py", "-m", "iterations=1", "env=swimmer", "buffer.ratio=[0.5,0.2,0.3],[0.34,0.33,0.33]", f"hydra.sweep.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    summaries = sorted(tmp_path.glob("*/summary.json"))
    assert len(summaries) == 2
    ratios = sorted(json.loads(s.read_text())["ratio"] for s in summaries)
    assert ratios == [[0.34, 0.33, 0.33], [0.5, 0.2, 0.3]]
    # The same sweep again: every job has finished, says so and leaves its files as they are.
    files = {p: p.read_bytes() for p in sorted(tmp_path.rglob("*")) if p.is_file() and p.name != "multirun.yaml"}
    again = run_recipe("es_td3.py", "-m", "iterations=1", "env=swimmer", "buffer.ratio=[0.5,0.2,0.3],[0.34,0.33,0.33]", f"hydra.sweep.dir={tmp_path}")
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout.count("finished: ") == 2, again.stdout
    assert {p: p.read_bytes() for p in files} == files


@pytest.mark.parametrize(
    "override, field",
    [
        ("buffer.ratio=[0.5,0.5]", "buffer.ratio"),
        ("buffer.ratio=[-1,1,1]", "buffer.ratio"),
        ("es.sigma=0", "es.sigma"),
        ("es.population_size=7", "es.population_size"),
        ("env.id=Walker3-v5", "env.id"),
        ("buffer.min_size=10", "buffer.min_size"),
        ("buffer.mode=sharde", "buffer.mode"),
    ],
)
def test_bad_config_fails_fast_with_one_line(run_recipe, tmp_path, override, field):
    result = run_recipe("es_td3.py", override, f"hydra.run.dir={tmp_path}")
    assert result.returncode != 0
    message = result.stderr.strip().splitlines()
    assert len(message) == 1 and field in message[0], result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "metrics.csv").exists()


# What the two implementations agree on (docs/performance.md, "Fast against reference").
SAME_COLUMNS = ("iteration", "td3_frames", "es_frames", "total_frames", "td3_updates", "noisy_size", "overwritten", "buffer_mode")
ES_COLUMNS = ("eval_return", "es_eval_return", "es_average", "es_generation_mean_return", "es_generation_max_return")


def test_fast_and_reference_runs_agree(run_recipe, tmp_path):
    """implementation=fast and implementation=reference, same seed, tiny preset: the counters are
    equal; the ES mean's returns, which depend on ES returns only while no overwrite happens,
    agree to float32 rounding (the batched forward sums in another order than functional_call).
    The TD3 columns differ: the hand-written gradients and fused Adam round differently from
    autograd and the per-tensor Adam, and TD3's episodes amplify it from the first update on."""
    rows = {}
    for implementation in ("fast", "reference"):
        result = run_recipe("es_td3.py", f"implementation={implementation}", f"hydra.run.dir={tmp_path / implementation}", timeout=1200)
        assert result.returncode == 0, result.stderr[-3000:]
        rows[implementation] = read_metrics(tmp_path / implementation / "metrics.csv")
    fast, reference = rows["fast"], rows["reference"]
    assert len(fast) == len(reference) == 2 and list(fast[0]) == list(reference[0])
    for column in SAME_COLUMNS:
        assert [r[column] for r in fast] == [r[column] for r in reference], column
    assert not any(r["overwritten"] for r in fast)  # the premise of the ES comparison below
    for column in ES_COLUMNS:
        for got, want in zip((r[column] for r in fast), (r[column] for r in reference)):
            assert got == pytest.approx(want, rel=1e-4, abs=1e-4), column
