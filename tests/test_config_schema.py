"""The config every recipe composes (torchrl_esrl/run/schema.py, conf/): every recipe x env x
experiment preset composes and passes the value checks, with Hydra's compose API.

``python tests/test_config_schema.py DIR`` writes each composition, resolved, to ``DIR`` (one YAML
file per recipe, env and preset, and Hydra's own settings beside it): two checkouts' dumps
compared with ``diff -r`` show what a change to the schema or the YAML files changed.
"""
import re
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import torchrl_esrl  # noqa: F401  registers the typed schema with Hydra's ConfigStore

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
RECIPE_CONFIGS = ("config", "td3", "es", "cem_rl", "cem_rl_buffers")  # recipes/es_td3.py, td3.py, es.py, cem_rl.py, cem_rl_buffers.py
ENVS = (None, *sorted(p.stem for p in (CONF / "env").glob("*.yaml")))  # None: the config's own choice
EXPERIMENTS = (None, *sorted(p.stem for p in (CONF / "experiment").glob("*.yaml")))
HYDRA_KEYS = ("callbacks", "job.chdir", "run", "sweep", "job_logging", "runtime.choices")  # what conf/ sets of Hydra's node


def overrides(env, experiment) -> list[str]:
    return [*([f"env={env}"] if env else []), *([f"experiment={experiment}"] if experiment else [])]


def composed(config: str, env=None, experiment=None, extra=(), hydra: bool = False):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose(config, overrides=[*overrides(env, experiment), *extra], return_hydra_config=hydra)


def dump(config: str, env, experiment) -> str:
    """The job's config, resolved, then the parts of Hydra's node conf/ sets (unresolved: they hold the time)."""
    cfg = composed(config, env, experiment, hydra=True)
    job = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    hydra = {key: OmegaConf.select(cfg.hydra, key) for key in HYDRA_KEYS}
    return OmegaConf.to_yaml(job, resolve=True) + "# hydra\n" + OmegaConf.to_yaml(OmegaConf.create(hydra))


def dump_all(directory: Path) -> int:
    directory.mkdir(parents=True, exist_ok=True)
    count = 0
    for config in RECIPE_CONFIGS:
        for env in ENVS:
            for experiment in EXPERIMENTS:
                (directory / f"{config}-{env or 'default'}-{experiment or 'default'}.yaml").write_text(dump(config, env, experiment))
                count += 1
    return count


@pytest.mark.parametrize("experiment", EXPERIMENTS)
@pytest.mark.parametrize("config", RECIPE_CONFIGS)
def test_every_recipe_env_and_preset_composes_and_passes_the_checks(config, experiment):
    from torchrl_esrl.run.config import validate_config

    for env in ENVS:
        cfg = composed(config, env, experiment)
        validate_config(cfg)
        assert OmegaConf.missing_keys(cfg) == set(), (config, env, experiment)


def _leaves(node, prefix=""):
    for key, value in node.items():
        if isinstance(value, dict):
            yield from _leaves(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


TOP_CONFIGS = ("config", "es", "td3", "cem_rl")  # the recipe configs that list the schema themselves


def test_yaml_files_hold_only_what_differs_from_the_schema_defaults():
    from torchrl_esrl.run import schema

    defaults = dict(_leaves(OmegaConf.to_container(OmegaConf.structured(schema.RunConfig))))
    defaults.update(_leaves({"cem": OmegaConf.to_container(OmegaConf.structured(schema.CEMConfig))}))  # None until a recipe sets it
    files = [*(CONF / f"{c}.yaml" for c in RECIPE_CONFIGS), CONF / "common.yaml", *(CONF / "env").glob("*.yaml"), *(CONF / "experiment").glob("*.yaml")]
    for path in files:
        content = OmegaConf.to_container(OmegaConf.load(path)) or {}
        prefix = "env." if path.parent.name == "env" else ""
        for key, value in _leaves({k: v for k, v in content.items() if k not in ("defaults", "hydra")}, prefix):
            assert key in defaults, f"{path.name}: {key} is not a schema key"
            assert value != defaults[key], f"{path.name}: {key}: {value!r} is the schema's default (torchrl_esrl/run/schema.py); write it once"
    for config in TOP_CONFIGS:  # each recipe's top config composes the one schema first
        assert OmegaConf.load(CONF / f"{config}.yaml").defaults[0] == schema.SCHEMA_NAME
    for config in RECIPE_CONFIGS:
        assert OmegaConf.get_type(composed(config)) is schema.RunConfig


def test_nothing_under_run_or_report_names_an_algorithm():
    """The run plumbing and the report serve any recipe: no recipe's or algorithm's name is in their
    code, except the names that are also a component's config section (``td3``, ``es``: TD3 and
    OpenAI-ES). The paper's table is data (``docs/results/paper_table1.csv``)."""
    from torchrl_esrl.run import schema

    recipes = [p for p in (ROOT / "recipes").glob("*.py") if p.stem != "report"]
    names = {p.stem for p in recipes} | {name for p in recipes for name in re.findall(r'AlgorithmInfo\(\s*"(\w+)"', p.read_text())}
    names -= {item for item in schema.RunConfig.__dataclass_fields__}
    assert {"es_td3", "cem_rl_buffers", "es_td3_buffers", "cem_rl_buffers_shared"} <= names
    for path in [*(ROOT / "torchrl_esrl" / "run").glob("*.py"), *(ROOT / "torchrl_esrl" / "report").glob("*.py")]:
        found = names & set(re.findall(r"\w+", path.read_text()))
        assert not found, f"{path.name} names {sorted(found)}"


def test_every_key_has_its_default_and_every_free_value_a_check():
    from torchrl_esrl.run import schema
    from torchrl_esrl.run.config import CHECKS, schema_fields, section_of

    assert OmegaConf.missing_keys(OmegaConf.structured(schema.RunConfig)) == {"env.name", "env.id"}  # the env group's choice
    unchecked = set()
    for key, item, annotation in schema_fields(schema.RunConfig):
        check = item.metadata.get("check")
        if check is not None:
            assert check["kind"] in CHECKS, key
        elif "renamed" not in item.metadata and annotation not in ("bool", bool) and section_of(annotation) is None:
            unchecked.add(key)
    # the keys any value of their type suits (a name, a path, open mappings and lists)
    assert unchecked == {"env.name", "env.kwargs", "env.wrappers", "env.transforms", "resume"}


def _outside(check: dict):
    """A value the check refuses."""
    if check["kind"] == "number":
        if check["high"] is not None:
            return check["high"] + 1
        return check["low"] if check["low_open"] else check["low"] - 1
    return {"choice": "not_a_choice", "layers": [], "name": "' '", "host_port": "somewhere", "mapping": 3}.get(check["kind"])


def test_each_keys_check_refuses_a_value_outside_it_in_one_line():
    from torchrl_esrl.errors import ConfigError
    from torchrl_esrl.run import schema
    from torchrl_esrl.run.config import schema_fields, validate_config

    checked = 0
    for key, item, _ in schema_fields(schema.RunConfig):
        check = item.metadata.get("check")
        value = _outside(check) if check else None
        if value is None:
            continue
        cfg = composed("cem_rl", experiment="tiny", extra=[f"{key}={value}"])
        with pytest.raises(ConfigError) as error:
            validate_config(cfg)
        message = str(error.value)
        assert message.startswith(f"{key}: ") and "allowed" in message and "\n" not in message, (key, message)
        checked += 1
    assert checked >= 45


def test_renamed_and_added_keys_come_from_the_schema_and_old_configs_resume_in_todays_names():
    from torchrl_esrl.run.config import ADDED, RENAMED
    from torchrl_esrl.run.resume import in_todays_names

    assert set(RENAMED) == {"td3.fast", "mode"} and ADDED == {"env.kwargs": {}, "env.wrappers": [], "env.transforms": [], "td3.precision": "fp32"}
    old = {"implementation": "fast", "mode": "async", "td3": {"fast": False, "lr": 0.1}, "es": {"sigma": 0.1}, "env": {"id": "Walker2d-v5"}}
    today = in_todays_names(old)
    assert today == {"implementation": "reference", "mode": None, "td3": {"fast": None, "lr": 0.1, "precision": "fp32"}, "es": {"sigma": 0.1, "schedule": "async"},
                     "env": {"id": "Walker2d-v5", "kwargs": {}, "wrappers": [], "transforms": []}}
    assert old["td3"]["fast"] is False and "kwargs" not in old["env"]  # the saved config itself is left as it is


@pytest.mark.parametrize("override, config", [("td3.fast=true", "config"), ("mode=async", "td3")])
def test_a_renamed_key_names_what_replaced_it(override, config):
    from torchrl_esrl.errors import ConfigError
    from torchrl_esrl.run.config import validate_config

    with pytest.raises(ConfigError, match=r"^(td3\.fast: renamed to implementation \(|mode: renamed to es\.schedule \()"):
        validate_config(composed(config, extra=[override]))


PLUS_OVERRIDES = [(c, o) for c in RECIPE_CONFIGS for o in ("+td3.lrr=0.1", "++td3.lrr=0.1", "+lrr=1", "++es.lrr=1")] + [("cem_rl", "++cem.lrr=1")]


@pytest.mark.parametrize("config, override", PLUS_OVERRIDES)
def test_unknown_keys_added_with_plus_are_refused_in_one_line(config, override):
    from torchrl_esrl.errors import ConfigError
    from torchrl_esrl.run.config import validate_config

    key = override.lstrip("+").partition("=")[0]
    with pytest.raises(ConfigError, match=rf"^{re.escape(key)}: not a key of this config \(allowed: .*\)$"):
        validate_config(composed(config, extra=[override]))
    validate_config(composed(config, extra=["++env.kwargs.anything=1"]))  # an open mapping: gymnasium.make's keyword arguments


@pytest.mark.parametrize("override", ["td3.lrr=0.1", "+td3.lrr=0.1", "++td3.lrr=0.1"])
def test_unknown_key_on_the_command_line_is_one_line_exit_2(tmp_path, override):
    result = subprocess.run([sys.executable, str(ROOT / "recipes" / "es_td3.py"), "experiment=tiny", override, f"hydra.run.dir={tmp_path / 'run'}"],
                            cwd=ROOT, capture_output=True, text=True, timeout=300)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("config error: ") and "td3.lrr" in lines[0], result.stderr[-2000:]
    assert not (tmp_path / "run").exists()


if __name__ == "__main__":
    print(f"{dump_all(Path(sys.argv[1]))} configs written to {sys.argv[1]}")
