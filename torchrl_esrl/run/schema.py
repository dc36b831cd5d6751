"""How a config key is declared (its type, its default and its value check, once: Hydra
structured configs), and the keys of every run.

:class:`RunConfig` holds what every recipe's config has: the run's own keys (seed, iterations,
device, resume...) and the sections of the components the experiment presets scale for every
recipe (env, TD3, actor, OpenAI-ES, buffers, threshold, overwrite rule, evaluation, logger, Ray,
checkpoints). Their defaults are the paper's hyper-parameters (Table 2, Sections 4.2-4.3); every
departure is in docs/deviations.md. A section only some recipes have (an algorithm's own
hyper-parameters) is a dataclass declared beside its component or recipe with the same field
helpers, and a recipe that has it adds it: ``recipe_main(..., sections={"<key>": <dataclass>})``
registers :func:`recipe_schema`, RunConfig's keys and those sections, under ``<config>_schema``,
which its top config (``conf/<config>.yaml``) lists first (a recipe without sections of its own
lists ``run_schema``). So Hydra rejects unknown keys and wrong types while composing; the YAML
files hold only what differs from the defaults. A
field's check (``metadata["check"]``, made by :func:`number`, :func:`one_of`...) is run by
:func:`torchrl_esrl.run.config.validate_config`, and so is a section's ``check(section, key)``,
its checks across its own keys; checks across sections live there.

To add a key: add its field to its section, with its default and check. If runs checkpointed
before it existed must resume, make it :func:`added` (their configs get the default); a key that
changes name keeps its old one as :func:`renamed`.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field, fields, make_dataclass
from collections.abc import Mapping
from typing import Any, Callable, Dict, List, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

SCHEMA_NAME = "run_schema"  # the node the top config of a recipe without sections of its own lists first
SEED_LIMIT = 2**31 - 2000  # numpy seeds are < 2**32; the recipes add up to 1000 for their streams
# logger.backend -> the package its TorchRL logger needs ("" = no logger, csv = no extra package)
LOGGER_PACKAGES = {"": None, "csv": None, "tensorboard": "tensorboard", "wandb": "wandb", "mlflow": "mlflow", "trackio": "trackio"}


def _field(default, check: dict | None = None, **metadata):
    metadata = {**metadata, **({"check": check} if check else {})}
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: copy.deepcopy(default), metadata=metadata)
    return field(default=default, metadata=metadata)


def number(default, low=None, high=None, *, low_open: bool = False, high_open: bool = False, integer: bool = False, added: bool = False):
    """A finite number (an integer if ``integer``) in the given bounds; ``None`` passes where the type is Optional;
    ``added``: as :func:`added`."""
    return _field(default, {"kind": "number", "low": low, "high": high, "low_open": low_open, "high_open": high_open, "integer": integer},
                  **({"added": True} if added else {}))


def positive(default, integer: bool = False):
    return number(default, low=0, low_open=True, integer=integer)


def count(default):
    """An integer >= 1 (iterations, frames, episodes, sizes)."""
    return positive(default, integer=True)


def one_of(default, options: tuple = (), among: str | None = None, packages: dict | None = None, added: bool = False):
    """One of ``options``, then of ``among`` (the dotted name of the list, mapping or function of
    the component that owns the names, read when checked); ``packages``: value -> package it needs;
    ``added``: as :func:`added`."""
    return _field(default, {"kind": "choice", "options": options, "among": among, "packages": packages or {}}, **({"added": True} if added else {}))


def layers(default):
    """Hidden layer widths: a non-empty list of positive integers."""
    return _field(default, {"kind": "layers"})


def checked_by(default, function: str):
    """Checked by ``function`` (a dotted name) of the value; it raises the one-line ConfigError."""
    return _field(default, {"kind": "call", "function": function})


def checked(default, kind: str):
    """Checked by ``run/config.py``'s check of that kind: ``name`` (non-empty), ``host_port``, ``mapping``."""
    return _field(default, {"kind": kind})


def added(default):
    """A key added since runs were first checkpointed: a saved config without it resumes with ``default``."""
    return _field(default, added=True)


@dataclass(frozen=True)
class Renamed:
    """What replaced a key: its new name, how to write it, and the new value of an old one (resume)."""

    to: str
    how: str
    convert: Callable[[Any], Any] = lambda value: value


def renamed(to: str, how: str, convert: Callable[[Any], Any] | None = None):
    """An old key, kept unset so that a config using it gets ``renamed to <to> (<how>)`` instead of Hydra's unknown key."""
    return _field(None, renamed=Renamed(to, how, *([convert] if convert else [])))


@dataclass
class EnvConfig:
    """The task, as every part of the run plays it (torchrl_esrl/envs.py, EnvSpec); name and id from conf/env/."""

    name: str = MISSING
    id: str = checked_by(MISSING, "torchrl_esrl.envs.resolve_env_id")  # a gymnasium id or a short name; the closest known one is suggested
    max_episode_steps: Optional[int] = positive(None, integer=True)  # null: the env's own limit (1000 for the MuJoCo locomotion tasks)
    kwargs: Dict[str, Any] = added({})  # gymnasium.make keyword arguments, e.g. ++env.kwargs.terminate_when_unhealthy=false
    wrappers: List[Any] = added([])  # gymnasium wrappers, in order: [{_target_: gymnasium.wrappers.ClipReward, min_reward: -1, max_reward: 1}]
    transforms: List[Any] = added([])  # TorchRL transforms after DoubleToFloat: [{_target_: torchrl.envs.RewardScaling, loc: 0.0, scale: 0.1}]


@dataclass
class TD3Config:
    """TD3 (Fujimoto et al. 2018; TorchRL's TD3Loss and SoftUpdate), Algorithm 1's TD3 phase."""

    frames_per_iteration: int = count(100000)  # M
    frames_per_batch: int = count(1)  # env frames collected between update bursts (1 = Algorithm 1)
    updates_per_frame: float = positive(1.0)
    lr: float = positive(3.0e-4)  # alpha_TD3
    gamma: float = number(0.99, low=0, high=1)
    tau: float = number(0.005, low=0, high=1, low_open=True)
    policy_noise: float = number(0.2, low=0)
    noise_clip: float = number(0.5, low=0)
    policy_delay: int = count(2)
    exploration_noise: float = number(0.1, low=0)  # epsilon ~ N(0, 0.1)
    loss_function: str = one_of("l2", ("l2", "l1", "smooth_l1"))  # torchrl.objectives.utils.distance_loss
    critic_hidden: List[int] = layers([256, 256])
    critic_activation: str = one_of("relu", among="torchrl_esrl.modules.networks.ACTIVATIONS")
    fast: Optional[bool] = renamed("implementation", "implementation=fast, or implementation=reference for td3.fast=false", lambda fast: "fast" if fast else "reference")
    # uniform-random actions first (Fujimoto's start_timesteps); 0: Algorithm 1 acts with the noisy actor from the start
    random_frames: int = number(0, low=0, integer=True)
    # torch threads of the TD3 phase; null: this job's share of the cores the process may use (CPU affinity)
    # divided among the jobs run beside it (torchrl_esrl/threads.py; 2 cores, two joblib jobs: 1 each)
    num_threads: Optional[int] = number(None, low=1, integer=True)
    # fp32 | bf16: the TD3 losses under torch.autocast(bfloat16), float32 weights and Adam (TD3's `precision`; docs/deviations.md)
    precision: str = one_of("fp32", among="torchrl_esrl.objectives.td3.TD3.PRECISIONS", added=True)


@dataclass
class ActorConfig:
    hidden: List[int] = layers([256, 256])
    activation: str = one_of("tanh", among="torchrl_esrl.modules.networks.ACTIVATIONS")


@dataclass
class ESConfig:
    """OpenAI-ES (Salimans et al. 2017; torchrl_esrl/es/openes.py), Algorithm 1's ES phase."""

    generations_per_iteration: int = count(50)  # g
    population_size: int = count(120)  # 60 antithetic pairs
    antithetic: bool = True
    sigma: float = positive(0.005)
    lr: float = positive(0.001)  # alpha_ES (Adam)
    weight_decay: float = number(0.0, low=0)
    fitness_shaping: str = one_of("centered_ranks", ("centered_ranks", "none"))  # torchrl_esrl.es.openes.OpenES
    # sequential (Algorithm 1) | async: the iteration's ES generations run during the TD3 phase
    schedule: str = one_of("sequential", ("sequential", "async"))
    # auto | gym | mujoco_batch | ray (offspring on Ray workers, see `ray`)
    backend: str = one_of("auto", among="torchrl_esrl.collectors.backends.available_backends", packages={"ray": "ray"})


@dataclass
class BufferConfig:
    """The MultiBuffer (Section 3.1)."""

    ratio: List[float] = checked_by([0.5, 0.2, 0.3], "torchrl_esrl.data.multibuffer.validate_ratio")  # (a:b:c) = good : bad : noisy
    capacity: int = count(1000000)  # per buffer
    batch_size: int = count(256)
    min_size: int = count(25000)  # K: every buffer with a non-zero share must hold K items
    renormalize: bool = False  # sample from the ready buffers only, ratio renormalised
    mode: str = one_of("multi", ("multi", "shared"))  # multi (good/bad/noisy) | shared (one buffer for ES and TD3, ERL-style ablation)


@dataclass
class ThresholdConfig:
    fraction: float = number(0.9, low=0, high=1)  # threshold = best - (1 - fraction) * |best| (Section 3.1)


@dataclass
class OverwriteConfig:
    """The overwrite rule (Section 3.2)."""

    window: int = count(3)  # k: iterations averaged by the overwrite rule
    reset_optimizer: bool = True  # clear ES Adam moments when the mean is overwritten
    mode: str = one_of("hard", ("hard", "soft"))  # hard: mean <- TD3 actor (Algorithm 1) | soft: mean <- (1 - mix) mean + mix TD3 actor (Section 5)
    mix: float = number(0.5, low=0, high=1, low_open=True)  # soft overwrite's mixing rate, in (0, 1]


@dataclass
class EvalConfig:
    episodes: int = count(5)  # deterministic episodes per evaluation (overwrite rule, curves)
    final_episodes: int = count(10)  # episodes of the final evaluation in summary.json


@dataclass
class LoggerConfig:
    # csv | tensorboard | wandb | mlflow | trackio | '' (none); its package must be installed
    backend: str = one_of("csv", tuple(LOGGER_PACKAGES), packages={k: v for k, v in LOGGER_PACKAGES.items() if v})
    progress: bool = True  # tqdm progress bar
    print_config: bool = False  # print the resolved config at start (it is saved in <run dir>/.hydra/ anyway)


@dataclass
class CheckpointConfig:
    """<run dir>/checkpoints; written at every iteration boundary."""

    every_frames: int = number(0, low=0, integer=True)  # also every N TD3 frames (0: off)
    every_generations: int = number(0, low=0, integer=True, added=True)  # also every N ES generations of an iteration's ES phase run inline (0: off)
    keep_last: int = count(2)


@dataclass
class RayConfig:
    """es.backend=ray (torchrl_esrl/collectors/ray_backend.py; pip install -e ".[ray]")."""

    address: Optional[str] = checked(None, "host_port")  # null: start Ray on this machine; "auto" or "host:port": join a cluster
    num_workers: int = count(2)  # Ray actors, each evaluating a contiguous share of every population
    worker_backend: str = one_of("auto", ("auto",), among="torchrl_esrl.collectors.backends.LOCAL_BACKENDS")  # the local backend each actor runs
    num_cpus_per_worker: float = positive(1.0)
    worker_kwargs: Any = checked({}, "mapping")  # extra arguments of the worker backend


@dataclass
class RunConfig:
    """The keys of every recipe's config: the run's own, and one section per component the
    experiment presets scale (a recipe that does not read a section still has it)."""

    seed: int = number(0, low=0, high=SEED_LIMIT, integer=True)
    # fast | reference: reference is stock TorchRL end to end; fast swaps in pieces proven equal (docs/performance.md)
    implementation: str = one_of("fast", among="torchrl_esrl.run.implementation.IMPLEMENTATIONS")
    device: str = checked_by("cpu", "torchrl_esrl.run.config.validate_device")
    iterations: int = count(20)  # outer loop of Algorithm 1
    experiment_name: str = checked("paper", "name")  # the experiment preset's name (conf/experiment/)
    resume: Optional[str] = None  # a run directory: continue it from its last checkpoint
    # true: a new run, in <hydra.run.dir>-2 (-3...) if hydra.run.dir already holds a run (a finished run is never rerun)
    fresh: bool = False
    env: EnvConfig = field(default_factory=EnvConfig)
    td3: TD3Config = field(default_factory=TD3Config)
    actor: ActorConfig = field(default_factory=ActorConfig)
    es: ESConfig = field(default_factory=ESConfig)
    buffer: BufferConfig = field(default_factory=BufferConfig)
    threshold: ThresholdConfig = field(default_factory=ThresholdConfig)
    overwrite: OverwriteConfig = field(default_factory=OverwriteConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    mode: Optional[str] = renamed("es.schedule", "es.schedule=sequential or es.schedule=async")
    ray: RayConfig = field(default_factory=RayConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)


def schema_name(config_name: str) -> str:
    """The ConfigStore name of the schema of the recipe whose top config is ``conf/<config_name>.yaml``."""
    return f"{config_name}_schema"


def recipe_schema(config_name: str, sections: Mapping[str, type] | None = None) -> tuple[type, str]:
    """The schema of a recipe and the name its top config lists first: :class:`RunConfig` as
    ``run_schema`` without ``sections``; else RunConfig's keys and ``sections`` (key -> section
    dataclass, at its defaults), registered with Hydra's ConfigStore as ``<config_name>_schema``."""
    if not sections:
        return RunConfig, SCHEMA_NAME
    clash = sorted(set(sections) & {item.name for item in fields(RunConfig)})
    if clash:
        raise ValueError(f"sections {clash} are keys of every run's config already (torchrl_esrl/run/schema.py)")
    name = schema_name(config_name)
    schema = make_dataclass(
        "".join(part.title() for part in name.split("_")),
        # added: a saved config without a section (a run checkpointed before its recipe had it) resumes at its defaults
        [(key, section, field(default_factory=section, metadata={"added": True})) for key, section in sections.items()],
        bases=(RunConfig,),
    )
    schema.__doc__ = f"conf/{config_name}.yaml's keys: every run's (RunConfig) and {', '.join(sections)}."
    ConfigStore.instance().store(name=name, node=schema)
    return schema, name


ConfigStore.instance().store(name=SCHEMA_NAME, node=RunConfig)
