"""The learners of the TD3 phase (torchrl_esrl/objectives/learner.py, learners.py, ddpg.py, sac.py):
TD3, DDPG and SAC built from the real config, updated on batches of a real TorchRL replay buffer
filled by real InvertedPendulum frames; their state resumes exactly; the run plumbing finds them by
the Learner protocol (pieces line, threads, memory estimate); the recipes run them."""
import io
import json
import subprocess
from pathlib import Path

import pytest
import torch
from conftest import ROOT, recipe_command
from hydra import compose, initialize_config_dir
from tensordict.nn import TensorDictSequential
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_esrl.collectors.td3_collector import GymTD3Collector, make_frame_batches, make_td3_collector
from torchrl_esrl.data.multibuffer import TRANSITION_KEYS
from torchrl_esrl.envs import EnvSizes, make_train_env
from torchrl_esrl.errors import ConfigError
from torchrl_esrl.modules.networks import flat_parameters, make_actor
from torchrl_esrl.modules.population import PopulationActor
from torchrl_esrl.objectives import DDPG, SAC, TD3, Learner, make_learner
from torchrl_esrl.objectives.learners import LEARNERS, LearnerConfig, learner_holdings
from torchrl_esrl.run.implementation import implementation_line, implementations

CLASSES = {"td3": TD3, "ddpg": DDPG, "sac": SAC}


def config(learner: str, *extra: str):
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=[f"learner={learner}", "env=inverted_pendulum", "experiment=tiny", *extra])


def built(learner: str, seed: int = 0, *extra: str):
    cfg = config(learner, f"seed={seed}", *extra)
    torch.manual_seed(seed)
    env = make_train_env(cfg)
    return cfg, env, make_learner(cfg, env)


def filled_buffer(cfg, env, learner, frames: int = 600) -> TensorDictReplayBuffer:
    """A stock TorchRL replay buffer holding ``frames`` real frames the learner's exploration policy played."""
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(frames), batch_size=64)
    collector, batches = make_frame_batches(cfg, env, learner)
    while len(buffer) < frames:
        buffer.extend(next(batches).select(*TRANSITION_KEYS))
    collector.shutdown()
    return buffer


def state_bytes(learner) -> bytes:
    stream = io.BytesIO()
    torch.save(learner.state_dict(), stream)
    return stream.getvalue()


@pytest.mark.parametrize("name", list(LEARNERS))
def test_each_learner_learns_from_a_replay_buffer_batch_with_finite_losses(name):
    cfg, env, learner = built(name)
    assert isinstance(learner, CLASSES[name]) and isinstance(learner, Learner)
    assert cfg.learner.name == name  # conf/learner/<name>.yaml
    buffer = filled_buffer(cfg, env, learner)
    before = flat_parameters(learner.actor)
    losses = [learner.update(buffer.sample()) for _ in range(6)]
    assert learner.updates == 6
    assert {"critic_loss", "actor_loss"} <= set().union(*losses)
    assert all(torch.isfinite(torch.tensor(value)) for out in losses for value in out.values())
    assert not torch.equal(flat_parameters(learner.actor), before)  # the actor ES sees is the one trained
    metrics = learner.metrics()
    assert set(metrics) == ({"alpha"} if name == "sac" else set())
    if name == "sac":  # the temperature moved by Adam from alpha_init
        assert metrics["alpha"] != pytest.approx(cfg.learner.sac.alpha_init, rel=1e-6)


@pytest.mark.parametrize("name", list(LEARNERS))
def test_a_restored_learner_takes_exactly_the_next_update(name):
    """state_dict -> a fresh learner (another seed, other weights): the same next update, losses
    and parameters bit for bit, as the learner that saved it."""
    cfg, env, learner = built(name)
    buffer = filled_buffer(cfg, env, learner)
    for _ in range(3):
        learner.update(buffer.sample())
    saved = torch.load(io.BytesIO(state_bytes(learner)), weights_only=False)
    _, _, restored = built(name, 1)
    assert not torch.equal(flat_parameters(restored.actor), flat_parameters(learner.actor))
    restored.load_state_dict(saved)
    assert restored.updates == 3 and torch.equal(flat_parameters(restored.actor), flat_parameters(learner.actor))
    batch = buffer.sample()
    torch.manual_seed(11)  # SAC samples its actions and next actions
    expected = learner.update(batch.clone())
    torch.manual_seed(11)
    assert restored.update(batch.clone()) == expected
    assert state_bytes(restored) == state_bytes(learner)


@pytest.mark.parametrize("name", ["ddpg", "sac"])
def test_the_pieces_line_names_the_stock_path_for_ddpg_and_sac(name):
    cfg, env, learner = built(name)
    collector, _ = make_frame_batches(cfg, env, learner)
    from torchrl_esrl.collectors.td3_collector import TD3EnvState

    pieces = implementations(cfg, td3=learner, td3_env=TD3EnvState(collector))
    collector.shutdown()
    stock = {"td3_loss": f"{'DDPGLoss' if name == 'ddpg' else 'SACLoss'} with autograd runs", "soft_update": "SoftUpdate runs", "adam": "torch.optim.Adam runs"}
    for piece, words in stock.items():
        assert pieces[piece].startswith(f"reference (learner={name}: ") and words in pieces[piece], pieces[piece]
    # DDPG acts as TD3 does (actor + Gaussian noise), which the fast collector steps exactly; SAC samples its policy.
    assert pieces["td3_collector"] == ("fast" if name == "ddpg" else "reference (the policy must be the actor followed by AdditiveGaussianModule)")
    assert implementation_line(pieces).startswith(f"pieces: td3_loss reference (learner={name}: ")
    reference = implementations(config(name, "implementation=reference"), td3=learner)
    assert set(reference.values()) == {"reference"}  # not asked for: no reason given


def test_td3_reports_its_fast_pieces_through_the_protocol():
    cfg, _, learner = built("td3")
    assert implementations(cfg, td3=learner) == {"td3_loss": "fast", "soft_update": "fast", "adam": "fast"}


def test_ddpg_exploration_is_stepped_by_the_fast_collector_as_by_torchrls_collector():
    cfg, env, learner = built("ddpg")
    assert isinstance(learner.exploration_policy, TensorDictSequential) and GymTD3Collector.supports(env, learner)

    def frames(fast: bool):
        _, env, ddpg = built("ddpg", 0, "td3.random_frames=0", "env.max_episode_steps=40")
        collector = GymTD3Collector(env, ddpg, 25) if fast else make_td3_collector(env, ddpg, 25)
        torch.manual_seed(7)
        batches = iter(collector)
        out = torch.cat([next(batches) for _ in range(4)])
        collector.shutdown()
        return out

    fast, reference = frames(True), frames(False)
    assert reference["next", "done"].any()  # an episode ended inside the window
    for key in TRANSITION_KEYS:
        assert torch.equal(fast.get(key), reference.get(key)), key


def test_sacs_deterministic_actor_is_its_policys_mean_path_and_what_es_searches():
    cfg, env, sac = built("sac")
    observations = torch.randn(32, env.observation_spec["observation"].shape[-1]) * 3
    from tensordict import TensorDict

    td = TensorDict(observation=observations, batch_size=[32])
    policy = sac.exploration_policy  # es_td3's config: no random warm-up around it
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        mode = policy(td.clone())["action"]
    with torch.no_grad():
        torch.testing.assert_close(sac.actor(td.clone())["action"], mode, rtol=1e-5, atol=1e-5)
    # ES's vector: make_actor's parameters (the mean path), not the scale head
    reference = make_actor(observations.shape[-1], env.action_spec, tuple(cfg.actor.hidden), cfg.actor.activation)
    assert flat_parameters(sac.actor).numel() == flat_parameters(reference).numel()
    assert sum(p.numel() for p in sac.exploration_policy.parameters()) == flat_parameters(reference).numel() + (cfg.actor.hidden[-1] + 1) * 1
    assert PopulationActor.supports(sac.actor)  # the batched ES forward evaluates it
    with set_exploration_type(ExplorationType.RANDOM):
        sampled = policy(td.clone())["action"]
    assert not torch.allclose(sampled, mode)  # acting samples the policy


@pytest.mark.parametrize("name", list(LEARNERS))
def test_the_memory_estimate_counts_what_each_learner_holds(name):
    """learner_holdings (before anything is built) against what the built learner holds after updates:
    its loss's networks and targets, its optimisers' moments and the exploration policy's copy."""
    cfg, env, learner = built(name)
    buffer = filled_buffer(cfg, env, learner, 300)
    for _ in range(2):
        learner.update(buffer.sample())
    optimizers = [learner.actor_optimizer, learner.critic_optimizer] if name == "td3" else list(learner.optimizers.values())
    tensors = [*learner.loss.parameters(), *learner.loss.buffers(), *(v for o in optimizers for state in o.state.values() for v in state.values() if torch.is_tensor(v))]
    held = sum(t.numel() for t in tensors if t.is_floating_point() and t.numel() > 1) + sum(p.numel() for p in learner.exploration_policy.parameters())
    sizes = EnvSizes(observation_dim=env.observation_spec["observation"].shape[-1], action_dim=env.action_spec.shape[-1], episode_steps=100)
    estimated = sum(h.bytes for h in learner_holdings(cfg, sizes))
    assert estimated == pytest.approx(4 * held, rel=1e-4)  # float32; the scalars left out above are a few bytes


def test_bfloat16_is_refused_for_another_learner_before_any_work():
    with pytest.raises(ConfigError, match=r"^td3.precision: 'bf16' is TD3's alone \(allowed: fp32 with learner.name=sac\)$"):
        learner_holdings(config("sac", "td3.precision=bf16"), EnvSizes(4, 1, 100))


def test_the_learner_sections_are_typed_checked_and_set_by_their_group():
    from torchrl_esrl.run.config import validate_config

    cfg = config("sac", "learner.sac.actor_lr=1e-3")
    assert cfg.learner.sac.actor_lr == 1e-3 and cfg.learner.sac.alpha_lr == 3e-4 and cfg.learner.ddpg.actor_lr == 3e-4
    with pytest.raises(ConfigError, match=r"^learner.sac.tau: 2.0 is invalid \(allowed: a number in \(0, 1\]\)$"):
        validate_config(config("sac", "learner.sac.tau=2.0"))
    with pytest.raises(Exception, match="bad_key"):
        config("ddpg", "learner.ddpg.bad_key=1")
    assert config("td3").learner.name == "td3"  # the default run's learner


@pytest.mark.e2e
@pytest.mark.parametrize(("script", "overrides", "words"), [
    ("es_td3.py", ["learner=foo"], "Could not find 'learner/foo' (allowed: ddpg, sac, td3)"),
    ("td3.py", ["learner=sac", "learner.sac.alpha_init=0"], "learner.sac.alpha_init: 0.0 is invalid (allowed: a number > 0)"),
    ("cem_rl.py", ["learner=sac"], "Could not override 'learner'"),  # CEM-RL's gradient steps are TD3's
])
def test_a_bad_learner_is_refused_in_one_line_before_any_work(tmp_path, script, overrides, words):
    result = subprocess.run(recipe_command(script, *overrides, f"hydra.run.dir={tmp_path / 'run'}"), cwd=ROOT, capture_output=True, text=True, timeout=300)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("config error: ") and words in lines[0], result.stderr[-2000:]
    assert not (tmp_path / "run").exists()


@pytest.mark.e2e
@pytest.mark.parametrize("script", ["es_td3.py", "td3.py"])
@pytest.mark.parametrize("name", ["ddpg", "sac"])
def test_the_recipes_run_ddpg_and_sac_to_their_summary(run_recipe, tmp_path, script, name):
    result = run_recipe(script, f"learner={name}", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["algorithm"] == (f"es_{name}_buffers" if script == "es_td3.py" else name)
    assert summary["td3_updates"] > 0 and summary["threads"]["td3"] >= 1
    assert summary["pieces"]["td3_loss"].startswith(f"reference (learner={name}: ")
    header = (tmp_path / "metrics.csv").read_text().splitlines()[0].split(",")
    assert ("alpha" in header) == (name == "sac")
    saved = (tmp_path / ".hydra" / "config.yaml").read_text()
    assert f"  name: {name}" in saved and f"  {name}:" in saved


def test_the_learner_recipes_compose_the_learner_section_and_its_group():
    from omegaconf import OmegaConf

    for name in ("config", "td3"):
        with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
            assert OmegaConf.get_type(compose(name).learner) is LearnerConfig
        assert {"learner": "td3"} in OmegaConf.load(ROOT / "conf" / f"{name}.yaml").defaults
    assert sorted(p.stem for p in Path(ROOT / "conf" / "learner").glob("*.yaml")) == sorted(LEARNERS)


# Short phases with checkpoints every 100 TD3 frames and 60-step episodes: a mid-phase checkpoint lands mid-episode, after learning began.
RESUME = ["env=halfcheetah", "env.max_episode_steps=60", "td3.frames_per_iteration=200", "td3.frames_per_batch=20", "buffer.min_size=64",
          "buffer.batch_size=64", "buffer.capacity=2000", "eval.episodes=1", "eval.final_episodes=1", "checkpoint.every_frames=100"]


def rows(run_dir):
    from torchrl_esrl.run.metrics import read_metrics

    return [{k: v for k, v in row.items() if k != "wall_time_s"} for row in read_metrics(Path(run_dir) / "metrics.csv")]


@pytest.mark.e2e
@pytest.mark.parametrize(("script", "name"), [("es_td3.py", "sac"), ("td3.py", "ddpg")])
def test_a_run_with_another_learner_killed_mid_phase_resumes_to_the_same_records(tmp_path, script, name):
    """SIGKILL after the first mid-phase checkpoint, then the same command: the uninterrupted run's
    metrics (SAC: TorchRL's Collector sampling the policy; DDPG: the fast collector after the warm-up)."""
    import os
    import signal
    import time

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    reference, killed = tmp_path / "reference", tmp_path / "killed"

    def command(run_dir):
        return recipe_command(script, f"learner={name}", *RESUME, f"hydra.run.dir={run_dir}")

    finished = subprocess.run(command(reference), cwd=ROOT, capture_output=True, text=True, timeout=1800, env=env)
    assert finished.returncode == 0, finished.stderr[-3000:]
    process = subprocess.Popen(command(killed), cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    deadline = time.monotonic() + 1800
    while not (killed / "checkpoints" / "checkpoint-000000000100").exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    process.send_signal(signal.SIGKILL)
    assert process.wait() == -signal.SIGKILL and not (killed / "metrics.csv").exists()
    resumed = subprocess.run(command(killed), cwd=ROOT, capture_output=True, text=True, timeout=1800, env=env)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert rows(killed) == rows(reference) and len(rows(reference)) == 2
    assert float(rows(reference)[-1]["td3_updates"]) > 100  # it learned before and after the kill
