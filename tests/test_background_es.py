"""es.schedule=async: ES generations in a background thread while the main thread trains TD3."""
import json
import threading

import pytest
import torch

from torchrl_esrl.algorithm.background_es import Guarded
from torchrl_esrl.algorithm.es_phase import ESPhase
from torchrl_esrl.data.multibuffer import MultiBuffer
from torchrl_esrl.envs import make_env
from torchrl_esrl.es.openes import OpenES
from torchrl_esrl.collectors.es_collector import ESCollector
from torchrl_esrl.run.metrics import read_metrics
from torchrl_esrl.modules.networks import flat_parameters, make_actor
from torchrl_esrl.data.threshold import Threshold


def swimmer_parts(generations=3):
    actor = make_actor(8, make_env("swimmer").action_spec)
    es = OpenES(flat_parameters(actor), population_size=4, sigma=0.05, lr=0.01, generator=torch.Generator().manual_seed(1))
    collector = ESCollector("swimmer", actor, backend="gym", max_episode_steps=50, seed=3)
    buffer = MultiBuffer(ratio=(0.5, 0.2, 0.3), capacity=5000, batch_size=32, min_size=32, renormalize=True)
    return es, collector, buffer, Threshold(0.9), generations


def in_background(es, collector, buffer, threshold, generations):
    """The BackgroundES of an async ES phase, with the lock-guarded buffer and threshold."""
    phase = ESPhase(es, collector, buffer, threshold, generations, shared_buffer=False, background=True)
    return phase.background, phase.buffer, phase.threshold


def test_background_generations_overlap_the_main_thread_and_route_every_transition():
    es, collector, buffer, threshold, generations = swimmer_parts()
    mean_before = es.mean.detach().clone()
    background, buffer, threshold = in_background(es, collector, buffer, threshold, generations)
    noisy = collector.evaluate_policy(mean_before, 1, seeds=[0]).transitions  # stand-in TD3 batch, 50 transitions
    main_steps_while_es_ran = 0
    background.start()
    while not background.future.done():  # the main thread keeps writing, reading and sampling meanwhile
        buffer.extend(noisy, "noisy")
        threshold.observe(-1e9)
        if buffer.ready():
            assert buffer.sample().batch_size == torch.Size([32])
        main_steps_while_es_ran += 1
    returns = background.join()
    background.close()
    assert main_steps_while_es_ran > 0
    assert len(returns) == generations and all(r.shape == (4,) for r in returns)
    sizes = buffer.sizes()
    assert sizes["good"] + sizes["bad"] == collector.frames == generations * 4 * 50  # Swimmer never terminates
    assert sizes["noisy"] == min(5000, 50 * main_steps_while_es_ran)
    assert threshold.best == max(r.max().item() for r in returns)
    assert not torch.equal(es.mean.detach(), mean_before)  # the ES mean moved in the thread


def test_errors_in_the_es_thread_surface_at_join():
    es, collector, buffer, threshold, _ = swimmer_parts()
    es = OpenES(torch.zeros(es.num_parameters + 1), population_size=4)  # wrong size: the collector rejects it in the thread
    background, _, _ = in_background(es, collector, buffer, threshold, 1)
    background.start()
    with pytest.raises(ValueError, match="parameters per member"):
        background.join()
    background.close()


def test_es_phase_inline_and_in_the_background_give_the_same_generations():
    """One interface (start, then finish) for both modes; with nothing else writing, the same result."""
    results = []
    for background in (False, True):
        torch.manual_seed(0)  # the same actor initialisation
        es, collector, buffer, threshold, generations = swimmer_parts(generations=2)
        phase = ESPhase(es, collector, buffer, threshold, generations, shared_buffer=False, background=background)
        assert phase.inline is not background and (phase.buffer is buffer) is not background  # guarded in the background
        phase.start()
        returns = phase.finish()
        phase.close()
        results.append((torch.cat(returns.returns), es.mean.detach().clone(), phase.buffer.sizes(), returns.metrics()))
    (inline_returns, inline_mean, inline_sizes, inline_metrics), (returns, mean, sizes, metrics) = results
    assert torch.equal(inline_returns, returns) and torch.equal(inline_mean, mean) and inline_sizes == sizes
    assert metrics == inline_metrics and metrics["es_generation_max_return"] == returns.max().item()


def test_guarded_calls_hold_the_lock():
    lock = threading.RLock()
    seen = []

    class Probe:
        value = 3

        def call(self):
            seen.append(lock._is_owned())
            return 7

    guarded = Guarded(Probe(), lock)
    assert guarded.call() == 7 and seen == [True] and guarded.value == 3


@pytest.mark.e2e
def test_recipe_async_mode_same_frames_as_sequential(run_recipe, tmp_path):
    result = run_recipe("es_td3.py", "env=swimmer", "es.schedule=async", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    rows = read_metrics(tmp_path / "metrics.csv")
    assert [r["td3_frames"] for r in rows] == [400, 800]
    assert [r["es_frames"] for r in rows] == [800, 1600]  # 2 generations x 4 offspring x 100 steps per iteration
    assert rows[-1]["good_size"] + rows[-1]["bad_size"] == 1600 and rows[-1]["noisy_size"] == 800
    assert rows[-1]["td3_updates"] > 0
    assert json.loads((tmp_path / "summary.json").read_text())["es_frames"] == 1600


@pytest.mark.e2e
def test_unknown_schedule_fails_fast(run_recipe, tmp_path):
    result = run_recipe("es_td3.py", "es.schedule=hogwild", f"hydra.run.dir={tmp_path}")
    assert result.returncode != 0 and "es.schedule" in result.stderr.strip().splitlines()[-1]
    assert "Traceback" not in result.stderr


@pytest.mark.e2e
def test_the_old_mode_key_is_a_one_line_error_naming_es_schedule(run_recipe, tmp_path):
    result = run_recipe("es_td3.py", "mode=async", f"hydra.run.dir={tmp_path / 'run'}")
    assert result.returncode == 2 and result.stderr.strip().splitlines() == ["config error: mode: renamed to es.schedule (es.schedule=sequential or es.schedule=async)"]
    assert not (tmp_path / "run").exists()
