"""Typed schema of ``conf/config.yaml`` (Hydra structured config) and one-line config errors.

The dataclasses give every key of the config a type; ``conf/config.yaml`` lists the schema
first in its defaults, so Hydra rejects unknown keys and values of the wrong type while
composing, before anything runs. Values themselves live in the YAML files (``???`` here).
A key added to the YAML must be added here too.

:func:`run_cli` calls a ``@hydra.main`` function so that configuration errors (Hydra's, OmegaConf's
and :class:`~torchrl_esrl.run.config.ConfigError`) come out as one line on stderr and exit 2,
without a traceback. :class:`ValidateBeforeRun` is a Hydra callback that runs the value checks
before Hydra writes anything into the run directory.
"""
from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field
from typing import Any, List, Optional

from hydra.core.config_store import ConfigStore
from hydra.experimental.callback import Callback
from omegaconf import MISSING

SCHEMA_NAME = "es_td3_schema"


@dataclass
class EnvConfig:
    name: str = MISSING
    id: str = MISSING
    max_episode_steps: Optional[int] = None


@dataclass
class TD3Config:
    frames_per_iteration: int = MISSING
    frames_per_batch: int = MISSING
    updates_per_frame: float = MISSING
    lr: float = MISSING
    gamma: float = MISSING
    tau: float = MISSING
    policy_noise: float = MISSING
    noise_clip: float = MISSING
    policy_delay: int = MISSING
    exploration_noise: float = MISSING
    loss_function: str = MISSING
    critic_hidden: List[int] = MISSING
    critic_activation: str = MISSING
    fast: bool = MISSING
    num_threads: Optional[int] = MISSING


@dataclass
class ActorConfig:
    hidden: List[int] = MISSING
    activation: str = MISSING


@dataclass
class ESConfig:
    generations_per_iteration: int = MISSING
    population_size: int = MISSING
    antithetic: bool = MISSING
    sigma: float = MISSING
    lr: float = MISSING
    weight_decay: float = MISSING
    fitness_shaping: str = MISSING
    backend: str = MISSING


@dataclass
class BufferConfig:
    ratio: List[float] = MISSING
    capacity: int = MISSING
    batch_size: int = MISSING
    min_size: int = MISSING
    renormalize: bool = MISSING
    mode: str = MISSING


@dataclass
class ThresholdConfig:
    fraction: float = MISSING


@dataclass
class OverwriteConfig:
    window: int = MISSING
    reset_optimizer: bool = MISSING


@dataclass
class EvalConfig:
    episodes: int = MISSING
    final_episodes: int = MISSING


@dataclass
class LoggerConfig:
    backend: str = MISSING
    progress: bool = MISSING


@dataclass
class CheckpointConfig:
    every_frames: int = 0  # also checkpoint every N TD3 frames (0: iteration boundaries only)
    keep_last: int = 2  # checkpoints kept in <run_dir>/checkpoints


@dataclass
class RayConfig:
    """es.backend=ray (torchrl_esrl/collectors/ray_backend.py)."""

    address: Optional[str] = None  # None: start Ray on this machine; "auto" or "host:port": join a cluster
    num_workers: int = 2
    worker_backend: str = "auto"
    num_cpus_per_worker: float = 1
    worker_kwargs: Any = field(default_factory=dict)


@dataclass
class CEMConfig:
    """CEM-RL baseline (recipes/cem_rl.py, torchrl_esrl/es/cem.py); unused by ES-TD3Buffers."""

    population_size: int = 10
    rl_fraction: float = 0.5
    elite_fraction: float = 0.5
    sigma_init: float = 1.0e-3
    damping_init: float = 1.0e-3
    damping_end: float = 1.0e-5
    damping_tau: float = 0.95


@dataclass
class ESTD3Config:
    """The whole config of ``recipes/es_td3.py``."""

    seed: int = MISSING
    device: str = MISSING
    iterations: int = MISSING
    experiment_name: str = MISSING
    resume: Optional[str] = None  # a run directory to continue from its last checkpoint
    env: EnvConfig = field(default_factory=EnvConfig)
    td3: TD3Config = field(default_factory=TD3Config)
    actor: ActorConfig = field(default_factory=ActorConfig)
    es: ESConfig = field(default_factory=ESConfig)
    buffer: BufferConfig = field(default_factory=BufferConfig)
    threshold: ThresholdConfig = field(default_factory=ThresholdConfig)
    overwrite: OverwriteConfig = field(default_factory=OverwriteConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    mode: str = "sequential"  # sequential | async (torchrl_esrl/algorithm/background_es.py)
    ray: RayConfig = field(default_factory=RayConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    cem: Optional[CEMConfig] = None  # only conf/cem_rl.yaml sets it


def register_schema() -> None:
    ConfigStore.instance().store(name=SCHEMA_NAME, node=ESTD3Config)


register_schema()


class ValidateBeforeRun(Callback):
    """Hydra callback: value checks before Hydra creates or writes the run directory."""

    def on_run_start(self, config, **kwargs: Any) -> None:
        from torchrl_esrl.run.checkpoint import prepare_run
        from torchrl_esrl.errors import ConfigError

        try:
            prepare_run(config, config.hydra.run.dir)
        except ConfigError as error:
            # Hydra turns a callback's Exception into a warning and goes on: exit here instead.
            print(f"config error: {error}", file=sys.stderr)
            raise SystemExit(2) from None


def one_line(error: BaseException) -> str:
    """A configuration error as one line: the field, the value and what is allowed."""
    from omegaconf.errors import OmegaConfBaseException

    cause = error
    while cause.__cause__ is not None and not isinstance(cause, OmegaConfBaseException):
        cause = cause.__cause__
    message = str(cause).strip().splitlines()[0] if str(cause).strip() else type(cause).__name__
    full_key = getattr(cause, "full_key", None)
    if isinstance(cause, OmegaConfBaseException) and full_key and not message.startswith(str(full_key)):
        message = f"{full_key}: {message}"
    if cause is not error and str(error).strip():
        message = f"{message} ({str(error).strip().splitlines()[0]})"
    options = getattr(error, "options", None)  # hydra's MissingConfigException: a config group choice
    if options:
        message = f"{message} (allowed: {', '.join(sorted(options))})"
    return message


def run_cli(main) -> None:
    """Call a ``@hydra.main`` function; config errors exit 2 with one line on stderr."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from torchrl_esrl.errors import ConfigError

    full_error = os.environ.get("HYDRA_FULL_ERROR")
    os.environ["HYDRA_FULL_ERROR"] = "1"  # let Hydra raise instead of printing a multi-line report
    try:
        main()
    except (ConfigError, HydraException, OmegaConfBaseException) as error:
        if full_error == "1":
            raise
        print(f"config error: {one_line(error)}", file=sys.stderr)
        raise SystemExit(2) from None
