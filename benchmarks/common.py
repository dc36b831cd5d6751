"""Helpers shared by the benchmarks: interleaved timing, synthetic transitions, machine info.

Every figure is a ratio against a baseline measured in the same run: the machine (2 cores) is
shared, so absolute rates move by up to 1.6x between minutes (docs/performance.md).
:func:`interleaved` runs baseline and candidates in turn, repetition after repetition, and reports
medians.
"""
from __future__ import annotations

import os

if os.environ.get("BENCHMARKS_OMP_PASSIVE"):  # set by a benchmark's --omp-passive; default: libgomp's own policy, as the recipes run
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads (see docs/performance.md)
import platform
import statistics
import time
from collections.abc import Callable, Mapping

import torch
from tensordict import TensorDict

# Observation / action sizes of the paper's tasks (gymnasium v5).
SHAPES = {"HalfCheetah-v5": (17, 6), "Ant-v5": (105, 8), "Walker2d-v5": (17, 6), "Hopper-v5": (11, 3), "Swimmer-v5": (8, 2)}


def transitions(n: int, obs_dim: int, act_dim: int, generator: torch.Generator | None = None) -> TensorDict:
    """``n`` random transitions with the MultiBuffer's key set (``buffers.TRANSITION_KEYS``)."""
    g = generator
    return TensorDict(
        {
            "observation": torch.randn(n, obs_dim, generator=g),
            "action": torch.rand(n, act_dim, generator=g) * 2 - 1,
            "next": {
                "observation": torch.randn(n, obs_dim, generator=g),
                "reward": torch.randn(n, 1, generator=g),
                "done": torch.zeros(n, 1, dtype=torch.bool),
                "terminated": torch.zeros(n, 1, dtype=torch.bool),
                "truncated": torch.zeros(n, 1, dtype=torch.bool),
            },
        },
        batch_size=[n],
    )


def fill(buffer, n: int, obs_dim: int, act_dim: int, chunk: int = 100_000, name: str | None = None) -> None:
    """Write ``n`` random transitions into a TorchRL buffer (or one MultiBuffer part) in chunks."""
    g = torch.Generator().manual_seed(0)
    for start in range(0, n, chunk):
        data = transitions(min(chunk, n - start), obs_dim, act_dim, g)
        buffer.extend(data) if name is None else buffer.extend(data, name)


def on_threads(threads: int | None, fn: Callable[[], None]) -> Callable[[], None]:
    """``fn`` as a method of :func:`interleaved` that runs on ``threads`` torch threads (None: as it
    finds them) and leaves the count as it was."""
    from torchrl_esrl.threads import torch_threads

    def call():
        with torch_threads(threads):
            fn()
    return call


def interleaved(methods: Mapping[str, Callable[[], None]], calls: int, repeats: int, warmup: int = 3) -> dict[str, dict]:
    """Seconds per call of each method: ``repeats`` rounds, each timing ``calls`` calls of every
    method in turn; median and all rounds reported."""
    for fn in methods.values():
        for _ in range(warmup):
            fn()
    rounds: dict[str, list[float]] = {name: [] for name in methods}
    for _ in range(repeats):
        for name, fn in methods.items():
            start = time.perf_counter()
            for _ in range(calls):
                fn()
            rounds[name].append((time.perf_counter() - start) / calls)
    return {name: {"s_per_call": statistics.median(r), "best_s_per_call": min(r), "rounds_s_per_call": r} for name, r in rounds.items()}


def machine() -> dict:
    return {
        "cpus": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
        "cpu": cpu_model(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY"),
        "cuda": torch.cuda.is_available(),
        "load_average": os.getloadavg(),
    }


# Instruction sets that decide the speed of the matrix products (bfloat16 on AMX needs amx_bf16).
CPU_FLAGS = ("avx2", "avx512f", "avx512_bf16", "amx_bf16", "amx_tile")


def cpu_model() -> dict:
    """The processor's model name, family/model numbers and :data:`CPU_FLAGS`, from /proc/cpuinfo
    (empty elsewhere): a virtual machine of the same size may run on another processor from one
    session to the next, and a figure holds for the processor it was measured on."""
    try:
        text = open("/proc/cpuinfo").read()
    except OSError:
        return {}
    first = dict(line.split(":", 1) for line in text.split("\n\n")[0].splitlines() if ":" in line)
    first = {key.strip(): value.strip() for key, value in first.items()}
    flags = set(first.get("flags", "").split())
    return {"model_name": first.get("model name"), "family": first.get("cpu family"), "model": first.get("model"),
            "flags": [flag for flag in CPU_FLAGS if flag in flags]}


def save_report(report: dict, out: str | None) -> dict:
    """Attach the machine description and write ``report`` as JSON to ``out`` (if given)."""
    report["machine"] = machine()
    if out:
        from pathlib import Path
        import json

        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps(report, indent=2))
    return report
