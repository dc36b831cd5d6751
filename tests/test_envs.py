"""The task's one description (torchrl_esrl/envs.py): a key given twice is one value or refused,
and a transform is described before its first reset."""
import pytest

from torchrl_esrl.envs import EnvSpec, describe_transform
from torchrl_esrl.errors import ConfigError


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
