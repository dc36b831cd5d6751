"""Typed schema of ``conf/config.yaml`` (Hydra structured config): types only, the values live in the YAML.

The dataclasses give every key of the config a type; ``conf/config.yaml`` lists the schema
first in its defaults, so Hydra rejects unknown keys and values of the wrong type while
composing, before anything runs. Values themselves live in the YAML files (``???`` here).
A key added to the YAML must be added here too.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

SCHEMA_NAME = "es_td3_schema"


@dataclass
class EnvConfig:
    """The task, as every part of the run plays it (torchrl_esrl/envs.py, EnvSpec)."""

    name: str = MISSING
    id: str = MISSING
    max_episode_steps: Optional[int] = MISSING
    kwargs: Dict[str, Any] = field(default_factory=dict)  # gymnasium.make keyword arguments, e.g. ++env.kwargs.terminate_when_unhealthy=false
    wrappers: List[Any] = field(default_factory=list)  # gymnasium wrappers, in order: [{_target_: gymnasium.wrappers.ClipReward, min_reward: -1, max_reward: 1}]
    transforms: List[Any] = field(default_factory=list)  # TorchRL transforms after DoubleToFloat: [{_target_: torchrl.envs.RewardScaling, loc: 0.0, scale: 0.1}]


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
    fast: Optional[bool] = None  # renamed: the top-level `implementation` (config.py names it)
    random_frames: int = MISSING
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
    schedule: str = MISSING
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
    mode: str = MISSING
    mix: float = MISSING


@dataclass
class EvalConfig:
    episodes: int = MISSING
    final_episodes: int = MISSING


@dataclass
class LoggerConfig:
    backend: str = MISSING
    progress: bool = MISSING
    print_config: bool = MISSING


@dataclass
class CheckpointConfig:
    every_frames: int = MISSING
    keep_last: int = MISSING


@dataclass
class RayConfig:
    """es.backend=ray (torchrl_esrl/collectors/ray_backend.py)."""

    address: Optional[str] = MISSING
    num_workers: int = MISSING
    worker_backend: str = MISSING
    num_cpus_per_worker: float = MISSING
    worker_kwargs: Any = MISSING


@dataclass
class CEMConfig:
    """CEM-RL baseline (recipes/cem_rl.py, torchrl_esrl/es/cem.py); unused by ES-TD3Buffers."""

    population_size: int = MISSING
    rl_fraction: float = MISSING
    elite_fraction: float = MISSING
    sigma_init: float = MISSING
    damping_init: float = MISSING
    damping_end: float = MISSING
    damping_tau: float = MISSING
    antithetic: bool = MISSING
    start_frames: int = MISSING


@dataclass
class ESTD3Config:
    """The whole config of ``recipes/es_td3.py``."""

    seed: int = MISSING
    implementation: str = MISSING
    device: str = MISSING
    iterations: int = MISSING
    experiment_name: str = MISSING
    resume: Optional[str] = MISSING
    fresh: bool = MISSING
    env: EnvConfig = field(default_factory=EnvConfig)
    td3: TD3Config = field(default_factory=TD3Config)
    actor: ActorConfig = field(default_factory=ActorConfig)
    es: ESConfig = field(default_factory=ESConfig)
    buffer: BufferConfig = field(default_factory=BufferConfig)
    threshold: ThresholdConfig = field(default_factory=ThresholdConfig)
    overwrite: OverwriteConfig = field(default_factory=OverwriteConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    mode: Optional[str] = None  # renamed: es.schedule (config.py names it)
    ray: RayConfig = field(default_factory=RayConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    cem: Optional[CEMConfig] = None  # only conf/cem_rl.yaml has this section


def register_schema() -> None:
    ConfigStore.instance().store(name=SCHEMA_NAME, node=ESTD3Config)


register_schema()
