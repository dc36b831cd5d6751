"""The config every recipe composes (torchrl_esrl/run/schema.py, a recipe's own sections, conf/):
every recipe x env x experiment preset composes and passes the value checks, with Hydra's compose
API; the recipes are found in recipes/ (tests/conftest.py's ``RECIPES``).

``python tests/test_config_schema.py DIR`` writes each composition, resolved, to ``DIR`` (one YAML
file per recipe, env and preset, and Hydra's own settings beside it): two checkouts' dumps
compared with ``diff -r`` show what a change to the schema or the YAML files changed.
"""
import dataclasses
import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import RECIPES, outside, own_keys, recipe_of
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
RECIPE_CONFIGS = tuple(recipe_of(script).config_name for script in RECIPES)  # each schema registered as its recipe was loaded
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


def test_yaml_files_hold_only_what_differs_from_the_schema_defaults():
    defaults = {}
    for script in RECIPES:  # every run's keys and each recipe's own sections
        defaults.update(_leaves(OmegaConf.to_container(OmegaConf.structured(recipe_of(script).schema))))
    files = [*(CONF / f"{c}.yaml" for c in RECIPE_CONFIGS), CONF / "common.yaml", *(CONF / "env").glob("*.yaml"), *(CONF / "experiment").glob("*.yaml")]
    for path in files:
        content = OmegaConf.to_container(OmegaConf.load(path)) or {}
        prefix = "env." if path.parent.name == "env" else ""
        for key, value in _leaves({k: v for k, v in content.items() if k not in ("defaults", "hydra")}, prefix):
            assert key in defaults, f"{path.name}: {key} is not a schema key"
            assert value != defaults[key], f"{path.name}: {key}: {value!r} is the schema's default (torchrl_esrl/run/schema.py, or the section's own); write it once"
    for script in RECIPES:  # each recipe's top config composes its schema, listed first
        recipe = recipe_of(script)
        assert OmegaConf.load(CONF / f"{recipe.config_name}.yaml").defaults[0] == recipe.schema_name, script
        composed_type = OmegaConf.get_type(composed(recipe.config_name))  # by name and fields: loading a recipe again registers a new class
        assert composed_type.__qualname__ == recipe.schema.__qualname__, script
        assert [f.name for f in dataclasses.fields(composed_type)] == [f.name for f in dataclasses.fields(recipe.schema)], script


def test_nothing_under_run_or_report_names_an_algorithm():
    """The run plumbing and the report serve any recipe: no recipe's or algorithm's name is in their
    code, except the names that are also a component's config section (``td3``, ``es``: TD3 and
    OpenAI-ES). The paper's table is data (``docs/results/paper_table1.csv``)."""
    recipes = [ROOT / "recipes" / script for script in RECIPES]
    names = {p.stem for p in recipes} | {info.name for script in RECIPES for info in RECIPES[script].ALGORITHMS}
    names -= {item for script in RECIPES for item in recipe_of(script).schema.__dataclass_fields__}
    assert {"es_td3", "cem_rl_buffers", "es_td3_buffers", "cem_rl_buffers_shared"} <= names
    for path in [*(ROOT / "torchrl_esrl" / "run").glob("*.py"), *(ROOT / "torchrl_esrl" / "report").glob("*.py")]:
        found = names & set(re.findall(r"\w+", path.read_text()))
        assert not found, f"{path.name} names {sorted(found)}"


@pytest.mark.parametrize("script", sorted(RECIPES))
def test_every_key_has_its_default_and_every_free_value_a_check(script):
    from torchrl_esrl.run.config import CHECKS, schema_fields, section_of

    schema = recipe_of(script).schema
    assert OmegaConf.missing_keys(OmegaConf.structured(schema)) == {"env.name", "env.id"}  # the env group's choice
    unchecked = set()
    for key, item, annotation in schema_fields(schema):
        check = item.metadata.get("check")
        if check is not None:
            assert check["kind"] in CHECKS, key
        elif "renamed" not in item.metadata and annotation not in ("bool", bool) and section_of(annotation) is None:
            unchecked.add(key)
    # the keys any value of their type suits (a name, a path, open mappings and lists)
    assert unchecked == {"env.name", "env.kwargs", "env.wrappers", "env.transforms", "resume"}


def _refused_in_one_line(config: str, key: str, value) -> None:
    from torchrl_esrl.errors import ConfigError
    from torchrl_esrl.run.config import validate_config

    cfg = composed(config, experiment="tiny", extra=[f"{key}={value}"])
    with pytest.raises(ConfigError) as error:
        validate_config(cfg)
    message = str(error.value)
    assert message.startswith(f"{key}: ") and "allowed" in message and "\n" not in message, (key, message)


def test_each_keys_check_refuses_a_value_outside_it_in_one_line():
    from torchrl_esrl.run.config import schema_fields
    from torchrl_esrl.run.schema import RunConfig

    checked = 0
    for key, item, _ in schema_fields(RunConfig):
        check = item.metadata.get("check")
        value = outside(check) if check else None
        if value is not None:
            _refused_in_one_line("config", key, value)
            checked += 1
    assert checked >= 45


@pytest.mark.parametrize("script", sorted(RECIPES))
def test_each_key_of_a_recipes_own_sections_refuses_a_value_outside_it_in_one_line(script):
    """The keys a recipe declares beside itself or its component (``recipe_main``'s ``sections``)
    are checked as every run's are."""
    config = recipe_of(script).config_name
    for key, item in own_keys(script):
        check = item.metadata.get("check")
        if check and outside(check) is not None:
            _refused_in_one_line(config, key, outside(check))


def test_renamed_and_added_keys_come_from_the_schema_and_old_configs_resume_in_todays_names():
    from torchrl_esrl.run.config import added_keys, renamed_keys
    from torchrl_esrl.run.resume import in_todays_names

    assert set(renamed_keys()) == {"td3.fast", "mode"} and added_keys() == {"env.kwargs": {}, "env.wrappers": [], "env.transforms": [], "td3.precision": "fp32",
                                                                                  "checkpoint.every_generations": 0}
    old = {"implementation": "fast", "mode": "async", "td3": {"fast": False, "lr": 0.1}, "es": {"sigma": 0.1}, "env": {"id": "Walker2d-v5"}}
    today = in_todays_names(old)
    assert today == {"implementation": "reference", "mode": None, "td3": {"fast": None, "lr": 0.1, "precision": "fp32"}, "es": {"sigma": 0.1, "schedule": "async"},
                     "env": {"id": "Walker2d-v5", "kwargs": {}, "wrappers": [], "transforms": []}}
    assert old["td3"]["fast"] is False and "kwargs" not in old["env"]  # the saved config itself is left as it is
    # A recipe's own section (recipe_main's sections) that its runs saved before it had it: at its defaults.
    learner = in_todays_names(old, recipe_of("es_td3.py").schema)["learner"]
    assert learner["name"] == "td3" and learner["sac"]["alpha_init"] == 1.0


def _algorithm_recipes() -> dict[str, str]:
    """Each algorithm name a run's ``summary.json`` can hold -> the recipe that writes it."""
    return {info.name: script for script, module in RECIPES.items() for info in module.ALGORITHMS}


COMMITTED_RUNS = sorted(path.parent for path in (ROOT / "docs" / "results" / "runs").rglob("config.yaml"))


def test_the_committed_runs_configs_read_as_their_recipes_configs_today():
    """The saved config of a committed run of today's keys (every section of every recipe's config,
    those its recipe does not read null, as the code that ran it wrote them), read in today's names
    for its recipe, holds exactly the keys its recipe's config holds today and passes today's checks:
    such a run, killed, resumes under today's code (a resume compares the saved config with the
    command's, key by key). Runs older than a key added without ``added`` never could."""
    import json

    from torchrl_esrl.run.config import validate_config
    from torchrl_esrl.run.resume import in_todays_names

    recipes, keys, read = _algorithm_recipes(), {}, {}
    for run in COMMITTED_RUNS:
        script = recipes[json.loads((run / "summary.json").read_text())["algorithm"]]
        recipe = recipe_of(script)
        if script not in keys:
            keys[script] = {key for key, _ in _leaves(OmegaConf.to_container(composed(recipe.config_name), resolve=True))}
        saved = OmegaConf.to_container(OmegaConf.load(run / "config.yaml"))
        if not keys[script] <= {key for key, _ in _leaves(in_todays_names(saved, recipe.schema))}:
            continue  # older than a key today's config has
        today = in_todays_names(saved, recipe.schema)
        assert {key for key, _ in _leaves(today)} == keys[script], (run, {key for key, _ in _leaves(today)} ^ keys[script])
        validate_config(OmegaConf.create(today), recipe.schema)
        read[script] = read.get(script, 0) + 1
    assert set(read) >= {"es_td3.py", "td3.py", "es.py", "cem_rl.py", "cem_rl_buffers.py"} and sum(read.values()) >= 100, read


@pytest.mark.parametrize("override, config", [("td3.fast=true", "config"), ("mode=async", "td3")])
def test_a_renamed_key_names_what_replaced_it(override, config):
    from torchrl_esrl.errors import ConfigError
    from torchrl_esrl.run.config import validate_config

    with pytest.raises(ConfigError, match=r"^(td3\.fast: renamed to implementation \(|mode: renamed to es\.schedule \()"):
        validate_config(composed(config, extra=[override]))


PLUS_OVERRIDES = [(recipe_of(s).config_name, o) for s in RECIPES for o in ("+td3.lrr=0.1", "++td3.lrr=0.1", "+lrr=1", "++es.lrr=1")] + [
    (recipe_of(s).config_name, f"++{section}.lrr=1") for s in RECIPES for section in sorted({key.split(".")[0] for key, _ in own_keys(s)})]  # a recipe's own sections


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
