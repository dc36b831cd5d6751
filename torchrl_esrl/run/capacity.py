"""What a run will hold, estimated before any work, and checked against this machine.

A recipe lists what it builds as :class:`Holding` s (its ``holdings(cfg, sizes)``, passed to
:func:`~torchrl_esrl.run.lifecycle.recipe_main`): each component says what it holds, from the
config and the task's observation and action sizes, without allocating it:

- replay buffers at full capacity (:func:`~torchrl_esrl.data.multibuffer.buffer_holdings`):
  each transition holds what :data:`~torchrl_esrl.data.multibuffer.TRANSITION_KEYS` lists plus TorchRL's ``index``
  (:func:`bytes_per_transition`); a ``LazyTensorStorage`` allocates its whole capacity at the
  first write;
- an evolution strategy's population and noise, and one generation's transitions, held until
  they are routed to the buffers (:func:`~torchrl_esrl.es.strategy.strategy_holdings`);
- networks and optimiser states (:func:`~torchrl_esrl.objectives.td3.td3_holdings`).

:func:`estimate` adds them up, and one checkpoint on disk (what is checkpointed, plus a margin
for the manifests). :func:`check_capacity` refuses a run whose estimate exceeds the available
memory or the free disk of its run directory (``checkpoint.keep_last`` checkpoints are kept,
one more while a save is written), with one line naming what is needed, what is there and the
field to change.
"""
from __future__ import annotations

import math
import shutil
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from torchrl_esrl.errors import ConfigError

FLOAT = 4  # float32 observations, actions, rewards and parameters
CHECKPOINT_MARGIN = 2**20  # manifests, schemas and small components of one checkpoint


def bytes_per_transition(observation_dim: int, action_dim: int) -> int:
    """One stored transition: observation, next observation, action and reward (float32), the
    done, terminated and truncated flags (bool) and the storage's ``index`` (int64)."""
    return FLOAT * (2 * observation_dim + action_dim + 1) + 3 + 8


def mlp_parameters(sizes: list[int]) -> int:
    """Weights and biases of an MLP with layer widths ``sizes`` (input first)."""
    return sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:]))


@dataclass(frozen=True)
class Holding:
    """Bytes one part of a run holds in memory. ``part``: ``buffers``, ``networks``,
    ``population`` or ``generation`` (parts of one name add up); ``field``: the config key that
    sizes it, named by a refusal; ``checkpointed``: written to every checkpoint too (or to the
    checkpoints a stop writes: the largest one counts); ``in_memory``: false for bytes only a
    checkpoint adds (a copy of what memory already counts); ``on_device``: on the run's ``device``
    (GPU memory on ``cuda``), else on the host."""

    part: str
    bytes: int
    field: str
    checkpointed: bool = True
    on_device: bool = False
    in_memory: bool = True


def network_holding(copies: int, parameters: int, field: str) -> Holding:
    """``copies`` float32 vectors of ``parameters`` (a network, its target, optimiser moments)."""
    return Holding("networks", FLOAT * copies * parameters, field)


def population_holdings(parameters: int, population_size: int, antithetic: bool, episode_steps: int | None, transition: int, field: str) -> list[Holding]:
    """One generation of an evolution strategy: the population, its noise and, for mirrored
    sampling, the half drawn before mirroring; and its members' episodes until they are routed."""
    return [
        Holding("population", FLOAT * parameters * population_size * (4 + bool(antithetic)) // 2, field, checkpointed=False),
        Holding("generation", population_size * (episode_steps or 0) * transition, f"{field} or env.max_episode_steps", checkpointed=False),
    ]


@dataclass
class Estimate:
    """Bytes a run will hold in memory (by part) and one checkpoint's size on disk."""

    memory: dict[str, int] = field(default_factory=dict)
    fields: dict[str, str] = field(default_factory=dict)  # part -> the config key a refusal names
    buffer_memory: int = 0  # on cfg.device (the buffers' storage device)
    checkpoint: int = 0

    @property
    def memory_total(self) -> int:
        return sum(self.memory.values())


def estimate(holdings: Iterable[Holding]) -> Estimate:
    """What a run holds, from what its recipe builds (module docstring)."""
    result = Estimate(checkpoint=CHECKPOINT_MARGIN)
    for held in holdings:
        result.memory[held.part] = result.memory.get(held.part, 0) + (held.bytes if held.in_memory else 0)
        result.fields.setdefault(held.part, held.field)
        result.buffer_memory += held.bytes if held.on_device else 0
        result.checkpoint += held.bytes if held.checkpointed else 0
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
    from torchrl_esrl.run.checkpoint import CHECKPOINT_DIR  # here: the components that declare their holdings import this module

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
        fields = result.fields
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
