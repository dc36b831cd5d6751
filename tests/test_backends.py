"""The one registry of ES backends and the one resolution of ``es.backend`` (``auto``, and what
``implementation=reference`` may run)."""
import pytest
from hydra import compose, initialize_config_dir

from torchrl_esrl.collectors.backends import LOCAL_BACKENDS, resolve_backend
from torchrl_esrl.errors import ConfigError
from torchrl_esrl.collectors.backends import es_backend
from tests.conftest import ROOT


def test_auto_is_the_fastest_backend_with_the_fast_physics_and_gym_without():
    assert resolve_backend("auto", "HalfCheetah-v5") == "mujoco_batch"
    assert resolve_backend("auto", "Pendulum-v1") == "gym"  # mujoco_batch does not know the task
    assert resolve_backend("auto", "HalfCheetah-v5", fast_physics=False) == "gym"
    assert resolve_backend("gym", "HalfCheetah-v5") == "gym" and resolve_backend("ray", "HalfCheetah-v5", fast_physics=False) == "ray"


def test_an_explicit_fast_physics_without_it_or_an_unknown_name_is_a_one_line_config_error():
    with pytest.raises(ConfigError) as error:
        resolve_backend("mujoco_batch", "HalfCheetah-v5", fast_physics=False)
    message = str(error.value)
    assert "\n" not in message and message.startswith("es.backend: mujoco_batch") and "(allowed: auto, gym, ray, or implementation=fast)" in message
    with pytest.raises(ConfigError, match=r"^ray.worker_backend: unknown backend 'ray' \(allowed: auto, gym, mujoco_batch\)$"):
        resolve_backend("ray", "HalfCheetah-v5", field="ray.worker_backend", allowed=LOCAL_BACKENDS)
    with pytest.raises(ConfigError, match=r"^ray.worker_backend: mujoco_batch .*\(allowed: auto, gym, or implementation=fast\)$"):
        resolve_backend("mujoco_batch", "HalfCheetah-v5", fast_physics=False, field="ray.worker_backend", allowed=LOCAL_BACKENDS)


def _config(*overrides):
    with initialize_config_dir(str(ROOT / "conf"), version_base=None):
        return compose("config", overrides=["env=halfcheetah", *overrides])


def test_the_factory_resolves_es_backend_once_for_the_implementation():
    assert es_backend(_config("implementation=fast", "es.backend=auto"))[0] == "mujoco_batch"
    assert es_backend(_config("implementation=reference", "es.backend=auto")) == ("gym", {})
    backend, kwargs = es_backend(_config("implementation=reference", "es.backend=ray"))
    assert backend == "ray" and kwargs["worker_backend"] == "gym" and kwargs["num_workers"] >= 1  # the ray section, as RayBackend's arguments
    with pytest.raises(ConfigError, match="^es.backend: mujoco_batch"):
        es_backend(_config("implementation=reference", "es.backend=mujoco_batch"))
    with pytest.raises(ConfigError, match="^ray.worker_backend: mujoco_batch"):
        es_backend(_config("implementation=reference", "es.backend=ray", "ray.worker_backend=mujoco_batch"))
