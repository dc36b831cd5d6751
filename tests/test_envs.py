"""The env check before a run (torchrl_esrl/envs.py, ``EnvSpec.checked_sizes``): the configured env
(keywords, wrappers, transforms) is made, reset and stepped with real gymnasium, MuJoCo and TorchRL
in a child process; a value that fails there, gives a non-finite observation or reward, makes
MuJoCo's simulation unstable or ends the process is one line naming its key. The task's one
description: a key given twice is one value or refused, and a transform is described before its
first reset."""
import math
import sys
from pathlib import Path

import pytest
from conftest import ROOT
from omegaconf import OmegaConf

from torchrl_esrl.envs import EnvSpec, describe_transform
from torchrl_esrl.errors import ConfigError

sys.path.insert(0, str(Path(__file__).parent))  # native_abort: the wrapper that ends its process

SQRT = {"_target_": "math.sqrt", "_partial_": True}  # a domain error on a negative number
LOG = {"_target_": "torch.log", "_partial_": True}  # NaN on a negative number
CLIP = {"_target_": "gymnasium.wrappers.ClipReward", "min_reward": -1.0, "max_reward": 1.0}  # plays
SCALE = {"_target_": "torchrl.envs.RewardScaling", "loc": 0.0, "scale": 0.1}  # plays

REFUSED = [
    # (kwargs, wrappers, transforms), the key named, words of the line
    (({"ctrl_cost_weight": "abc"}, (), ()), "env.kwargs.ctrl_cost_weight", "fails at HalfCheetah-v5's step 1 (TypeError"),
    (({"reset_noise_scale": math.nan}, (), ()), "env.kwargs.reset_noise_scale", "fails at HalfCheetah-v5's reset (OverflowError"),
    (({"ctrl_cost_weight": math.nan}, (), ()), "env.kwargs.ctrl_cost_weight", "gives a non-finite reward (nan) at HalfCheetah-v5's step 1"),
    (({"ctrl_cost_weight": math.inf}, (), ()), "env.kwargs.ctrl_cost_weight", "gives a non-finite reward (-inf)"),
    (({"reset_noise_scale": 1e200}, (), ()), "env.kwargs.reset_noise_scale", "makes MuJoCo's simulation unstable"),
    (({"frame_skip": 0}, (), ()), "env.kwargs.frame_skip", "fails when HalfCheetah-v5 is made (ZeroDivisionError"),
    # the key whose addition makes the env fail, after keys that play
    (({"forward_reward_weight": 2.0, "reset_noise_scale": -1.0}, (), ()), "env.kwargs.reset_noise_scale", "fails at HalfCheetah-v5's reset (ValueError"),
    (({}, ({"_target_": "gymnasium.wrappers.TransformReward", "func": SQRT},), ()), "env.wrappers[0]: gymnasium.wrappers.TransformReward", "fails at HalfCheetah-v5's step 1 (ValueError: math domain error)"),
    (({}, (CLIP, {"_target_": "gymnasium.wrappers.ClipReward", "min_reward": math.nan, "max_reward": 1.0}), ()), "env.wrappers[1]: gymnasium.wrappers.ClipReward", "non-finite reward"),
    (({}, (), ({"_target_": "torchrl.envs.UnaryTransform", "in_keys": ["observation"], "out_keys": ["observation"], "fn": LOG},)), "env.transforms[0]: torchrl.envs.UnaryTransform", "non-finite observation (nan) at HalfCheetah-v5's reset"),
    (({}, (), ({"_target_": "torchrl.envs.UnaryTransform", "in_keys": ["observation"], "out_keys": ["observation"], "fn": SQRT},)), "env.transforms[0]", "fails when HalfCheetah-v5 is made"),
    (({}, (), (SCALE, {"_target_": "torchrl.envs.RewardScaling", "loc": 0.0, "scale": math.nan})), "env.transforms[1]: torchrl.envs.RewardScaling", "non-finite reward (nan)"),
    # a native crash: the child process ends, the run's process says which entry ends it
    (({}, ({"_target_": "native_abort.AbortAtStep"},), ()), "env.wrappers[0]: native_abort.AbortAtStep", "ends the process that plays HalfCheetah-v5 (signal SIGABRT: Fatal Python error: Aborted)"),
]


@pytest.mark.parametrize("given, key, words", REFUSED, ids=[case[1] + "-" + str(i) for i, case in enumerate(REFUSED)])
def test_an_env_that_fails_when_played_is_one_line_naming_its_key(given, key, words):
    kwargs, wrappers, transforms = given
    spec = EnvSpec("HalfCheetah-v5", kwargs, wrappers, transforms, max_episode_steps=100)
    with pytest.raises(ConfigError) as error:
        spec.checked_sizes()
    line = str(error.value)
    assert "\n" not in line and line.startswith(f"{key}") and words in line and "(allowed: " in line, line


@pytest.mark.parametrize("preset", sorted(p.stem for p in (ROOT / "conf" / "env").glob("*.yaml")))
def test_every_env_preset_plays_and_the_child_finds_the_sizes_found_here(preset):
    spec = EnvSpec.from_config(OmegaConf.load(ROOT / "conf" / "env" / f"{preset}.yaml"))
    assert spec.checked_sizes() == spec.sizes()


def test_wrappers_and_transforms_that_play_pass_with_their_sizes():
    spec = EnvSpec("HalfCheetah-v5", {"ctrl_cost_weight": 0.2}, (CLIP,), (SCALE,), max_episode_steps=100)
    sizes = spec.checked_sizes()
    assert (sizes.observation_dim, sizes.action_dim, sizes.episode_steps) == (17, 6, 100)


def test_the_time_limit_given_as_a_keyword_too_is_one_value():
    """``env.kwargs.max_episode_steps`` (gymnasium.make takes it) beside ``env.max_episode_steps``:
    equal, or given alone, it is the spec's one time limit (not a keyword the batched physics
    would have to reproduce); the env plays it."""
    for spec in (EnvSpec("Hopper-v5", {"max_episode_steps": 37}, max_episode_steps=37), EnvSpec("Hopper-v5", {"max_episode_steps": 37})):
        assert spec.kwargs == {} and spec.max_episode_steps == 37 and spec.plain
        assert spec.make_gym().spec.max_episode_steps == 37
    assert EnvSpec("Hopper-v5", {"max_episode_steps": None, "frame_skip": 2}, max_episode_steps=50).kwargs == {"frame_skip": 2}


@pytest.mark.parametrize(("value", "start"), [(37, "env.kwargs.max_episode_steps: 37 and env.max_episode_steps: 50 both set"), ("abc", "env.kwargs.max_episode_steps: 'abc' is invalid")])
def test_the_time_limit_given_twice_with_two_values_is_refused_naming_both_keys(value, start):
    with pytest.raises(ConfigError) as error:
        EnvSpec("Hopper-v5", {"max_episode_steps": value}, max_episode_steps=50)
    message = str(error.value)
    assert "\n" not in message and message.startswith(start) and "env.max_episode_steps" in message, message


@pytest.mark.e2e
def test_the_time_limit_given_twice_is_a_one_line_exit_2_before_the_run(run_recipe, tmp_path):
    run_dir = tmp_path / "run"
    result = run_recipe("es.py", "++env.kwargs.max_episode_steps=37", f"hydra.run.dir={run_dir}", timeout=300)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr[-2000:]
    assert lines[0].startswith("config error: env.kwargs.max_episode_steps: 37 and env.max_episode_steps: 100 both set") and not run_dir.exists(), lines


def test_a_transform_is_described_before_its_first_reset():
    """``CatFrames`` makes its frame buffer at the first reset: the description says so instead of
    failing, and the TD3 collector's comparison of the env's transforms can run on a fresh env."""
    from torchrl.envs import CatFrames

    spec = EnvSpec("Hopper-v5", transforms=({"_target_": "torchrl.envs.CatFrames", "N": 2, "dim": -1, "in_keys": ["observation"]},))
    env = spec.make_torchrl(seed=0)
    stack = next(t for t in env.transform if isinstance(t, CatFrames))
    name, _, buffers = describe_transform(stack)
    assert name.endswith(".CatFrames") and all(value == ("uninitialized",) for _, value in buffers) and buffers, buffers
    env.reset()
    assert all(value != ("uninitialized",) for _, value in describe_transform(stack)[2])
    assert spec.sizes().observation_dim == 2 * 11
