"""What a run will hold, estimated before any work, and checked against this machine.

:func:`estimate` sizes, from the config and the task's observation and action sizes:

- the replay buffers at full capacity (ES-TD3Buffers: good, bad and noisy, or one with
  ``buffer.mode=shared``; TD3 and CEM-RL: one; OpenAI-ES: none). Each transition holds what
  :data:`~torchrl_esrl.data.multibuffer.TRANSITION_KEYS` lists plus TorchRL's ``index``
  (:func:`bytes_per_transition`); a ``LazyTensorStorage`` allocates its whole capacity at the
  first write;
- the population of a generation and its noise (OpenAI-ES, or CEM-RL's CEM) and that
  generation's transitions, held until they are routed to the buffers;
- the networks and optimiser states (:func:`parameter_copies`);
- one checkpoint on disk: the buffers and the networks, plus a margin for the manifests.

:func:`check_capacity` refuses a run whose estimate exceeds the available memory or the free
disk of its run directory (``checkpoint.keep_last`` checkpoints are kept, one more while a
save is written), with one line naming what is needed, what is there and the field to change.
"""
from __future__ import annotations

import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from torchrl_esrl.envs import EnvSizes
from torchrl_esrl.errors import ConfigError
from torchrl_esrl.run.checkpoint import CHECKPOINT_DIR

FLOAT = 4  # float32 observations, actions, rewards and parameters
CHECKPOINT_MARGIN = 2**20  # manifests, schemas and small components of one checkpoint


def bytes_per_transition(observation_dim: int, action_dim: int) -> int:
    """One stored transition: observation, next observation, action and reward (float32), the
    done, terminated and truncated flags (bool) and the storage's ``index`` (int64)."""
    return FLOAT * (2 * observation_dim + action_dim + 1) + 3 + 8


def mlp_parameters(sizes: list[int]) -> int:
    """Weights and biases of an MLP with layer widths ``sizes`` (input first)."""
    return sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:]))


def parameter_copies(algorithm: str) -> tuple[int, int]:
    """(actor-sized, critic-sized) parameter vectors a run holds and checkpoints.

    TD3: actor, target actor, Adam's two moments (4) and twin critics, their targets and Adam's
    moments (8 critics); the exploration policy holds the actor once more. OpenAI-ES: the mean
    and Adam's two moments (3). CEM-RL's CEM: the mean and the diagonal variance (2)."""
    if algorithm.startswith("es_td3"):
        return 4 + 1 + 3, 8
    if algorithm == "td3":
        return 4 + 1, 8
    if algorithm == "cem_rl":
        return 4 + 2, 8
    return 3, 0  # es


def buffer_count(algorithm: str) -> int:
    if algorithm.startswith("es_td3_shared"):
        return 1
    if algorithm.startswith("es_td3"):
        return 3
    return 0 if algorithm == "es" else 1


def default_algorithm(cfg) -> str:
    """The algorithm a config runs when the recipe is not named (the ES-TD3 config, or CEM-RL's)."""
    if cfg.get("cem") is not None:
        return "cem_rl"
    return "es_td3_shared" if cfg.buffer.mode == "shared" else "es_td3_buffers"


@dataclass
class Estimate:
    """Bytes a run will hold in memory (by part) and one checkpoint's size on disk."""

    memory: dict[str, int] = field(default_factory=dict)
    buffer_memory: int = 0  # on cfg.device (the buffers' storage device)
    checkpoint: int = 0
    population_field: str = "es.population_size"

    @property
    def memory_total(self) -> int:
        return sum(self.memory.values())


def estimate(cfg, algorithm: str, sizes: EnvSizes) -> Estimate:
    """What a run of ``algorithm`` with ``cfg`` on a task of ``sizes`` holds (module docstring)."""
    transition = bytes_per_transition(sizes.observation_dim, sizes.action_dim)
    buffers = buffer_count(algorithm) * int(cfg.buffer.capacity) * transition
    actor = mlp_parameters([sizes.observation_dim, *cfg.actor.hidden, sizes.action_dim])
    critic = mlp_parameters([sizes.observation_dim + sizes.action_dim, *cfg.td3.critic_hidden, 1])
    actors, critics = parameter_copies(algorithm)
    networks = FLOAT * (actors * actor + critics * critic)
    result = Estimate(buffer_memory=buffers, checkpoint=buffers + networks + CHECKPOINT_MARGIN)
    result.memory["buffers"] = buffers
    result.memory["networks"] = networks
    if algorithm != "td3":
        cem = algorithm == "cem_rl"
        population = int(cfg.cem.population_size if cem else cfg.es.population_size)
        antithetic = bool(cfg.cem.antithetic if cem else cfg.es.antithetic)
        # the population, its noise and, for mirrored sampling, the half drawn before mirroring
        result.memory["population"] = FLOAT * actor * population * (4 + antithetic) // 2
        result.memory["generation"] = population * (sizes.episode_steps or 0) * transition
        result.population_field = "cem.population_size" if cem else "es.population_size"
    return result


def available_memory() -> int | None:
    """Memory this process can still take: ``MemAvailable`` of /proc/meminfo (psutil elsewhere)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        import psutil
    except ImportError:
        return None
    return int(psutil.virtual_memory().available)


def free_disk(path: Path) -> tuple[int, Path]:
    """Free bytes of the filesystem ``path`` will live on (its nearest existing parent)."""
    existing = Path(path).absolute()
    while not existing.exists():
        existing = existing.parent
    return shutil.disk_usage(existing).free, existing


def existing_checkpoints(run_dir: Path) -> int:
    """Bytes already taken by ``run_dir``'s checkpoints (replaced as the run goes on)."""
    directory = Path(run_dir) / CHECKPOINT_DIR
    if not directory.is_dir():
        return 0
    return sum(p.stat().st_blocks * 512 for p in directory.rglob("*") if p.is_file())


def human(count: float) -> str:
    """Bytes in decimal units: ``68.0 TB``."""
    units = ("B", "kB", "MB", "GB", "TB", "PB", "EB")
    power = min(int(math.log10(max(count, 1)) // 3), len(units) - 1)
    return f"{count / 1000 ** power:.1f} {units[power]}" if power else f"{int(count)} B"


def check_capacity(cfg, result: Estimate, run_dir: Path, memory: int | None = None, disk: tuple[int, Path] | None = None, gpu: int | None = None) -> None:
    """Raise :class:`ConfigError` if ``result`` exceeds the available memory (``memory``, by
    default :func:`available_memory`) or the free disk at ``run_dir`` (``disk``: free bytes and
    where; by default :func:`free_disk`)."""
    on_gpu = str(cfg.device).startswith("cuda")
    if on_gpu:  # the buffers live in GPU memory, the rest on the host
        free = gpu if gpu is not None else _gpu_free(cfg.device)
        if free is not None and result.buffer_memory > free:
            raise ConfigError(f"buffer.capacity: {cfg.buffer.capacity} transitions per buffer need {human(result.buffer_memory)} on {cfg.device}, {human(free)} free there (allowed: a smaller buffer.capacity, or device=cpu)")
    needed = result.memory_total - (result.buffer_memory if on_gpu else 0)
    memory = available_memory() if memory is None else memory
    if memory is not None and needed > memory:
        parts = {k: v for k, v in result.memory.items() if v and not (on_gpu and k == "buffers")}
        largest = max(parts, key=parts.get)
        fields = {"buffers": "buffer.capacity", "population": result.population_field, "generation": f"{result.population_field} or env.max_episode_steps", "networks": "actor.hidden or td3.critic_hidden"}
        listed = ", ".join(f"{name} {human(size)}" for name, size in parts.items())
        raise ConfigError(f"{fields[largest].split(' ')[0]}: this run needs about {human(needed)} of memory ({listed}), {human(memory)} is available (allowed: a smaller {fields[largest]})")
    free, where = free_disk(run_dir) if disk is None else disk
    keep = int(cfg.checkpoint.keep_last)
    needed = max(result.checkpoint, (keep + 1) * result.checkpoint - existing_checkpoints(run_dir))
    if needed > free:
        raise ConfigError(
            f"hydra.run.dir: checkpoints of this run need about {human(needed)} of disk ({human(result.checkpoint)} each, "
            f"{keep} kept and one more while saving), {human(free)} is free at {where} (allowed: a smaller buffer.capacity or checkpoint.keep_last, or a hydra.run.dir with more room)"
        )


def _gpu_free(device) -> int | None:
    import torch

    if not torch.cuda.is_available():
        return None
    return int(torch.cuda.mem_get_info(torch.device(str(device)))[0])
