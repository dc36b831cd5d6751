import os
import subprocess
import sys
from pathlib import Path

# Before anything imports Ray (tests/test_ray_backend.py): loopback-only node addresses, no usage
# reporting. Ray reads these at import; set later, its nodes advertise the host address and hang.
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
os.environ["RAY_USAGE_STATS_ENABLED"] = "0"

import pytest  # noqa: E402
import torch  # noqa: E402
from tensordict import TensorDict  # noqa: E402

torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))

from torchrl_esrl.run.algorithm_info import training_recipes  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TINY = "experiment=tiny"  # conf/experiment/tiny.yaml: the one budget of every test that runs a recipe
# Every recipe that trains (recipes/*.py whose main recipe_main built), by file name: the tests every
# recipe gets are parametrized over it, so a new recipe needs no edit of the tests.
RECIPES = training_recipes(ROOT / "recipes")


def recipe_of(script: str):
    """What ``recipes/<script>`` gave ``recipe_main``: its config name, schema, algorithm and holdings."""
    return RECIPES[script].main.recipe


def tiny_overrides(script: str) -> tuple[str, ...]:
    """What ``recipes/<script>`` needs on top of the tests' budget (its ``TINY_OVERRIDES``, if any)."""
    return tuple(getattr(RECIPES[script], "TINY_OVERRIDES", ()))


def own_keys(script: str) -> list[tuple[str, object]]:
    """``(key, field)`` of each key of the recipe's own config sections (none where it has none)."""
    from torchrl_esrl.run.config import schema_fields
    from torchrl_esrl.run.schema import RunConfig

    every_run = {key for key, _, _ in schema_fields(RunConfig)}
    return [(key, item) for key, item, _ in schema_fields(recipe_of(script).schema) if key not in every_run]


def outside(check: dict):
    """A value a key's check (``metadata["check"]`` of its schema field) refuses; None for a check without one."""
    if check["kind"] == "number":
        if check["high"] is not None:
            return check["high"] + 1
        if check["low"] is not None:
            return check["low"] if check["low_open"] else check["low"] - 1
        return None  # any number (SAC's target entropy)
    return {"choice": "not_a_choice", "layers": [], "name": "' '", "host_port": "somewhere", "mapping": 3}.get(check["kind"])


def transitions(n, fill=0.0, obs_dim=3, act_dim=1):
    """``n`` transitions with every key a MultiBuffer stores, valued ``fill``, plus one it drops."""
    return TensorDict(
        {
            "observation": torch.full((n, obs_dim), fill),
            "action": torch.zeros(n, act_dim),
            "next": {
                "observation": torch.full((n, obs_dim), fill),
                "reward": torch.full((n, 1), fill),
                "done": torch.zeros(n, 1, dtype=torch.bool),
                "terminated": torch.zeros(n, 1, dtype=torch.bool),
                "truncated": torch.zeros(n, 1, dtype=torch.bool),
            },
            "extra": torch.ones(n),  # dropped: not a transition key
        },
        batch_size=[n],
    )


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


def recipe_command(script: str, *overrides: str) -> list[str]:
    """``python recipes/<script> [-m] experiment=tiny <overrides>`` (Hydra wants -m first)."""
    multirun = [o for o in overrides if o == "-m"]
    return [sys.executable, str(ROOT / "recipes" / script), *multirun, TINY, *(o for o in overrides if o != "-m")]


def load_recipe(script: str):
    """The recipe module ``recipes/<script>``, imported (its ``ALGORITHMS``, ``holdings``, ``train``)."""
    from torchrl_esrl.run.algorithm_info import load_recipe as load

    return load(ROOT / "recipes" / script)


@pytest.fixture(scope="session")
def run_recipe():
    """Run a recipe with the tiny budget in a subprocess: ``run_recipe("es_td3.py", *overrides)``."""

    def run(script: str, *overrides: str, env: dict | None = None, timeout: int = 600) -> subprocess.CompletedProcess:
        return subprocess.run(recipe_command(script, *overrides), cwd=ROOT, capture_output=True, text=True, timeout=timeout, env=env)

    return run
