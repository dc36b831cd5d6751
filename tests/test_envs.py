"""The env check before a run (torchrl_esrl/envs.py, ``EnvSpec.checked_sizes``): the configured env
(keywords, wrappers, transforms) is made, reset and stepped with real gymnasium, MuJoCo and TorchRL
in a child process; a value that fails there, gives a non-finite observation or reward, makes
MuJoCo's simulation unstable or ends the process is one line naming its key."""
import math
import sys
from pathlib import Path

import pytest
from conftest import ROOT
from omegaconf import OmegaConf

from torchrl_esrl.envs import EnvSpec
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
