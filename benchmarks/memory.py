"""Peak memory of a paper-configured run (figure 5): three 1M-transition buffers of Ant-v5 (105-dim
observations, the largest of the paper's tasks), plus one ES generation in flight.

The storage is computed exactly from the layout ``LazyTensorStorage`` allocates for the MultiBuffer's
key set (buffers.TRANSITION_KEYS): per transition 2 x obs float32 + act float32 + reward float32 +
3 bool flags. The resident set size (RSS, /proc/self/status VmRSS) is then measured after filling the
three buffers at ``--capacity`` (default: the paper's 1M) and after creating one generation's
transitions (120 x 1000 Ant steps, the ES collector's layout); measured/computed is the check.

Goal: peak RSS < 24 GiB. Usage: ``python -m benchmarks.memory [--quick] [--capacity N] [--out PATH]``.
"""
from __future__ import annotations

import argparse
import gc
from pathlib import Path


from benchmarks.common import SHAPES, fill, save_report, transitions  # sets OMP_WAIT_POLICY, first

import torch

from torchrl_esrl.data.multibuffer import MultiBuffer

GIB = 2**30


def rss() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS")


def peak_rss() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmHWM")


def bytes_per_transition(obs_dim: int, act_dim: int) -> int:
    return 4 * (2 * obs_dim + act_dim + 1) + 3  # observation, next/observation, action, reward; done/terminated/truncated


def run(capacity: int = 1_000_000, env_id: str = "Ant-v5", members: int = 120, steps: int = 1000) -> dict:
    obs_dim, act_dim = SHAPES[env_id]
    gc.collect()
    before = rss()
    buffer = MultiBuffer(capacity=capacity)
    for name in buffer.names:
        fill(buffer, capacity, obs_dim, act_dim, name=name)
    gc.collect()
    after_fill = rss()
    in_flight = transitions(members * steps, obs_dim, act_dim)  # one generation's transitions
    in_flight.set("episode_return", torch.zeros(members * steps, 1))  # the collector's extra per-step keys
    after_generation = rss()
    computed = 3 * capacity * bytes_per_transition(obs_dim, act_dim)
    per_storage = bytes_per_transition(obs_dim, act_dim)
    paper = 3 * 1_000_000 * per_storage
    generation_bytes = sum(t.numel() * t.element_size() for t in in_flight.values(True, True))
    measured_buffers = after_fill - before
    projected_peak = before + paper + generation_bytes
    return {
        "env": env_id, "capacity": capacity, "bytes_per_transition": per_storage,
        "computed_buffers_bytes": computed, "measured_buffers_bytes": measured_buffers,
        "measured_over_computed": measured_buffers / computed,
        "rss_before_bytes": before, "rss_after_fill_bytes": after_fill, "rss_after_generation_bytes": after_generation,
        "generation_in_flight_bytes": generation_bytes, "peak_rss_bytes": peak_rss(),
        "paper_buffers_bytes": paper, "paper_projected_peak_bytes": projected_peak,
        "paper_projected_peak_gib": projected_peak / GIB, "goal": "peak < 24 GiB", "met": max(projected_peak, peak_rss()) < 24 * GIB,
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="100k-item buffers (computed figure still for 1M)")
    parser.add_argument("--capacity", type=int, default=None)
    parser.add_argument("--out", default="benchmarks/results/memory.json")
    args = parser.parse_args(argv)
    report = run(args.capacity or (100_000 if args.quick else 1_000_000))
    print(f"Ant-v5: {report['bytes_per_transition']} B/transition; 3 x {report['capacity']:,} buffers: computed "
          f"{report['computed_buffers_bytes'] / GIB:.3f} GiB, measured RSS growth {report['measured_buffers_bytes'] / GIB:.3f} GiB "
          f"({report['measured_over_computed']:.3f}x); generation in flight {report['generation_in_flight_bytes'] / GIB:.3f} GiB; "
          f"peak RSS {report['peak_rss_bytes'] / GIB:.2f} GiB; paper run projected {report['paper_projected_peak_gib']:.2f} GiB (< 24 GiB: {report['met']})")
    save_report(report, args.out)
    return report


if __name__ == "__main__":
    main()
