"""Fused Adam's step when some of its moments are denormal floats, against the same step without.

A critic weight whose gradient turns exactly zero and stays so (a ReLU unit that no longer fires
on any sample) has its first moment multiplied by beta1 = 0.9 at every step: after about 800 steps
it is a denormal float, and under round-to-nearest it stays one for good (0.9 x 4 x 2^-149 rounds
back to 4 x 2^-149); the second moment gets there after about 74k steps. The processor then takes a
slow path for every operation on it. `torch.optim.Adam(fused=True)` on the stacked twin critics of
the paper's sizes (two critics 23-256-256-1, Walker2d's input), with a fraction of each moment
tensor's entries denormal (their gradients zero) or none, interleaved in one process on one thread.

    python -m benchmarks.adam_denormal [--fraction 0.125] [--checkpoint <run checkpoint dir>] [--out PATH]

``--checkpoint`` also counts the denormal entries of a run checkpoint's TD3 state (the float32
tensors of its ``components/*-td3/state``: networks, targets, Adam's moments), to say what a real
run carries.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import interleaved, on_threads, save_report

STACKED_CRITIC_SHAPES = [(2, 256, 23), (2, 256), (2, 256, 256), (2, 256), (2, 1, 256), (2, 1)]
SMALLEST_NORMAL = float(np.finfo(np.float32).tiny)


def adam_with_moments(denormal_every: int | None, seed: int = 0) -> torch.optim.Adam:
    """Fused Adam over the stacked critics' shapes after one step, its moments random; with
    ``denormal_every = k``, every k-th entry of each moment tensor set to 4 x 2^-149 and its gradient
    to zero (the state such a weight reaches: the entry stays denormal under later steps)."""
    generator = torch.Generator().manual_seed(seed)
    params = [torch.nn.Parameter(torch.randn(shape, generator=generator)) for shape in STACKED_CRITIC_SHAPES]
    for param in params:
        param.grad = torch.randn(param.shape, generator=generator) * 1e-2
    adam = torch.optim.Adam(params, lr=3e-4, fused=True)
    adam.step()
    if denormal_every:
        for param in params:
            state = adam.state[param]
            for moment in (state["exp_avg"], state["exp_avg_sq"]):
                moment[..., ::denormal_every] = 4 * 2.0 ** -149
            param.grad[..., ::denormal_every] = 0.0
    return adam


def denormal_count(values: np.ndarray) -> int:
    """How many entries of a float32 array are denormal (non-zero, below the smallest normal float)."""
    return int(((values != 0) & (np.abs(values) < SMALLEST_NORMAL)).sum())


def denormal_fraction(tensors: list[torch.Tensor]) -> float:
    total = sum(t.numel() for t in tensors)
    return sum(denormal_count(t.numpy()) for t in tensors) / max(total, 1)


def checkpoint_denormals(checkpoint: Path) -> dict:
    """Per float32 tensor of the checkpoint's TD3 state (tensordict's memmap files): its shape and
    how many of its entries are denormal; tensors without one are left out."""
    state = next(checkpoint.glob("components/*-td3/state"))
    meta = json.loads((state / "meta.json").read_text())
    found, entries, denormal = {}, 0, 0
    for name, info in sorted(meta.items()):
        path = state / f"{name}.memmap"
        if not isinstance(info, dict) or info.get("dtype") != "torch.float32" or not path.exists():
            continue
        values = np.fromfile(path, dtype=np.float32)
        count = denormal_count(values)
        entries, denormal = entries + values.size, denormal + count
        if count:
            found[name] = {"shape": info.get("shape"), "denormal": count, "entries": int(values.size)}
    return {"checkpoint": str(checkpoint), "float32_entries": entries, "denormal_entries": denormal, "tensors": found}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fraction", type=float, default=0.125, help="share of each moment tensor's entries made denormal")
    parser.add_argument("--calls", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--checkpoint", type=Path, default=None)
    parser.add_argument("--out", default="benchmarks/results/adam_denormal.json")
    args = parser.parse_args(argv)
    if not 0 < args.fraction <= 1:
        parser.error(f"--fraction: {args.fraction} (allowed: a share in (0, 1])")
    every = max(1, round(1 / args.fraction))
    optimizers = {"normal": adam_with_moments(None), "denormal": adam_with_moments(every)}
    fractions = {name: denormal_fraction([t for s in adam.state.values() for t in (s["exp_avg"], s["exp_avg_sq"])]) for name, adam in optimizers.items()}
    timed = interleaved({name: on_threads(1, adam.step) for name, adam in optimizers.items()}, args.calls, args.repeats)
    report = {
        "command": "python -m benchmarks.adam_denormal " + " ".join(argv if argv is not None else sys.argv[1:]),
        "shapes": STACKED_CRITIC_SHAPES, "threads": 1, "moments_denormal": fractions, "methods": timed,
        "denormal_over_normal": timed["denormal"]["s_per_call"] / timed["normal"]["s_per_call"],
    }
    if args.checkpoint is not None:
        report["checkpoint"] = checkpoint_denormals(args.checkpoint)
    save_report(report, args.out)
    for name, result in timed.items():
        print(f"fused Adam step, {fractions[name]:.1%} of the moments denormal: {result['s_per_call'] * 1e3:.3f} ms (median of {args.repeats} rounds)")
    print(f"denormal / normal: {report['denormal_over_normal']:.1f}x")
    if args.checkpoint is not None:
        found = report["checkpoint"]
        print(f"{found['checkpoint']}: {found['denormal_entries']} of {found['float32_entries']} float32 entries of the TD3 state denormal")
    return report


if __name__ == "__main__":
    main()
