"""es.schedule=async vs es.schedule=sequential (Algorithm 1) at equal frames, on this machine, in one process.

    python benchmarks/async_vs_sequential.py [--iterations 3] [--repeats 2] [--env halfcheetah] [override ...]

Runs the recipe's ``train`` with the same seed and budget in both modes (``--repeats`` runs each,
in ABBA order), and prints wall
time per iteration, returns and their ratios (async / sequential), measured in the same run.
Writes benchmarks/results/async_vs_sequential.json.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from torchrl_esrl.run.lifecycle import Run
from torchrl_esrl.run.metrics import read_metrics

ROOT = Path(__file__).resolve().parents[1]

# Small budget where both halves cost seconds per iteration, so overlap is visible.
BUDGET = [
    "experiment=quick",
    "td3.frames_per_iteration=2000",
    "td3.frames_per_batch=50",
    "buffer.min_size=1000",
    "es.population_size=20",
    "es.generations_per_iteration=4",
    "eval.episodes=2",
    "eval.final_episodes=3",
    "logger.progress=false",
    "logger.backend=",
]


def load_train():
    spec = importlib.util.spec_from_file_location("es_td3_recipe", ROOT / "recipes" / "es_td3.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.train


def run(train, overrides: list[str]) -> dict:
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    with tempfile.TemporaryDirectory() as run_dir:
        start = time.perf_counter()
        summary = train(cfg, Run(cfg, Path(run_dir), "es_td3_buffers"))
        wall = time.perf_counter() - start
        rows = read_metrics(Path(run_dir) / "metrics.csv")
    times = [rows[0]["wall_time_s"]] + [b["wall_time_s"] - a["wall_time_s"] for a, b in zip(rows, rows[1:])]
    return {
        "wall_time_s": round(wall, 2),
        "iteration_times_s": [round(t, 2) for t in times],
        "mean_iteration_time_s": round(sum(times) / len(times), 2),
        "td3_frames": summary["td3_frames"],
        "es_frames": summary["es_frames"],
        "td3_updates": summary["td3_updates"],
        "final_es_mean_return": round(summary["final_es_mean_return"], 2),
        "final_td3_actor_return": round(summary["final_td3_actor_return"], 2),
        "td3_eval_returns": [round(r["td3_eval_return"], 2) for r in rows],
        "es_eval_returns": [round(r["es_eval_return"], 2) for r in rows],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=3)
    parser.add_argument("--env", default="halfcheetah")
    parser.add_argument("--repeats", type=int, default=2, help="runs per mode, in ABBA order")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "async_vs_sequential.json"))
    parser.add_argument("--torch-threads", type=int, default=int(os.environ.get("OMP_NUM_THREADS", "1")), help="run with OMP_NUM_THREADS set to the same value: OpenMP reads it per thread")
    parser.add_argument("overrides", nargs="*", help="extra Hydra overrides for both runs")
    args = parser.parse_args()
    torch.set_num_threads(args.torch_threads)
    train = load_train()
    common = [*BUDGET, f"env={args.env}", f"iterations={args.iterations}", *args.overrides]
    # ABBA order (sequential, async, async, sequential, ...): a machine whose load drifts during the
    # benchmark (shared CPUs) biases both modes alike.
    order = [m for r in range(args.repeats) for m in (("sequential", "async") if r % 2 == 0 else ("async", "sequential"))]
    runs: dict[str, list[dict]] = {"sequential": [], "async": []}
    for mode in order:
        result = run(train, [*common, f"es.schedule={mode}"])
        runs[mode].append(result)
        print(f"{mode:>10}: {result['mean_iteration_time_s']:.2f} s/iteration, ES mean {result['final_es_mean_return']:.1f}, TD3 actor {result['final_td3_actor_return']:.1f}", flush=True)
    seq, asy = runs["sequential"], runs["async"]
    assert {(r["td3_frames"], r["es_frames"]) for r in seq + asy} == {(seq[0]["td3_frames"], seq[0]["es_frames"])}, "modes must compare at equal frames"

    def mean(rs, key):
        return sum(r[key] for r in rs) / len(rs)

    results = runs
    ratios = {
        "iteration_time_async_over_sequential": round(mean(asy, "mean_iteration_time_s") / mean(seq, "mean_iteration_time_s"), 3),
        "iteration_time_ratio_per_pair": [round(a["mean_iteration_time_s"] / s["mean_iteration_time_s"], 3) for s, a in zip(seq, asy)],
        "wall_time_async_over_sequential": round(mean(asy, "wall_time_s") / mean(seq, "wall_time_s"), 3),
        "final_es_return_async_minus_sequential": round(mean(asy, "final_es_mean_return") - mean(seq, "final_es_mean_return"), 2),
        "final_td3_return_async_minus_sequential": round(mean(asy, "final_td3_actor_return") - mean(seq, "final_td3_actor_return"), 2),
    }
    print(json.dumps(ratios, indent=2))
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    report = {
        "overrides": common,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "torch_threads": torch.get_num_threads(), "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS"), "load_average_at_end": load},
        "results": results,
        "ratios": ratios,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(report, indent=2) + "\n")
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
