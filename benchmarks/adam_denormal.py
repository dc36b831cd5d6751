"""Fused Adam's step when some of its moments are denormal floats, against the same step without.

A critic weight whose gradient turns exactly zero and stays so (a ReLU unit that no longer fires
on any sample) has its first moment multiplied by beta1 = 0.9 at every step: after about 800 steps
it is a denormal float, and under round-to-nearest it stays one for good (0.9 x 4 x 2^-149 rounds
back to 4 x 2^-149); the second moment gets there after about 74k steps. The processor then takes a
slow path for every operation on it. `torch.optim.Adam(fused=True)` on the stacked twin critics of
the paper's sizes (two critics 23-256-256-1, Walker2d's input), with a fraction of each moment
tensor's entries denormal (their gradients zero) or none, interleaved in one process on one thread.

    python -m benchmarks.adam_denormal [--fraction 0.125] [--checkpoint <run checkpoint dir>] [--updates 400] [--out PATH]

``--checkpoint`` also counts the denormal entries of a run checkpoint's TD3 state (the float32
tensors of its ``components/*-td3/state``: networks, targets, Adam's moments), to say what a real
run carries, and times what they cost where it matters: the run's own TD3 update (its config from
the checkpoint, :func:`~torchrl_esrl.objectives.learners.make_learner`), restored from the
checkpoint with its buffers, on batches the run's MultiBuffer samples, 1 thread, interleaved in
three copies: the moments as saved, the same with ``torch.set_flush_denormal(True)`` around each
update, and the moments' denormal entries set to zero.
"""
from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import interleaved, on_threads, save_report

STACKED_CRITIC_SHAPES = [(2, 256, 23), (2, 256), (2, 256, 256), (2, 256), (2, 1, 256), (2, 1)]
SMALLEST_NORMAL = float(np.finfo(np.float32).tiny)


def adam_moments(optimizer: torch.optim.Optimizer) -> list[torch.Tensor]:
    return [t for state in optimizer.state.values() for t in (state["exp_avg"], state["exp_avg_sq"])]


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


def zero_denormal_moments(optimizer: torch.optim.Optimizer) -> None:
    for moment in adam_moments(optimizer):
        moment[(moment != 0) & (moment.abs() < SMALLEST_NORMAL)] = 0.0


def flushing_denormals(fn):
    """``fn`` run with the calling thread's denormals flushed to zero (inputs and results)."""
    def call():
        torch.set_flush_denormal(True)
        try:
            fn()
        finally:
            torch.set_flush_denormal(False)
    return call


def run_update_methods(checkpoint: Path, batches: int = 64) -> tuple[dict, dict]:
    """``(learners, methods)``: the run's TD3 learner restored from ``checkpoint`` in three copies
    (see the module's docstring), and for each a method taking one update on the next of ``batches``
    batches sampled from the restored MultiBuffer, on 1 thread."""
    from omegaconf import OmegaConf
    from torchrl.checkpoint import Checkpoint, StateDictCheckpointAdapter

    from torchrl_esrl.data.multibuffer import MultiBuffer, make_multibuffer
    from torchrl_esrl.envs import make_train_env
    from torchrl_esrl.objectives.learners import make_learner

    cfg = OmegaConf.create(json.loads((checkpoint / "manifest.json").read_text())["metadata"]["config"])
    env, buffer = make_train_env(cfg), make_multibuffer(cfg)
    learners = {name: make_learner(cfg, env) for name in ("as_saved", "as_saved_flush_denormal", "denormals_zeroed")}
    def restore(**components):
        Checkpoint(**components).register_adapter(MultiBuffer, StateDictCheckpointAdapter()).load(checkpoint, components=list(components))

    restore(buffer=buffer)  # once: the copies share it
    for learner in learners.values():
        restore(td3=learner)
    for optimizer in (learners["denormals_zeroed"].critic_optimizer, learners["denormals_zeroed"].actor_optimizer):
        zero_denormal_moments(optimizer)
    torch.manual_seed(0)
    sampled = [buffer.sample() for _ in range(batches)]

    def update(learner):
        position = itertools.count()
        return lambda: learner.update(sampled[next(position) % batches])

    methods = {name: update(learner) for name, learner in learners.items()}
    methods["as_saved_flush_denormal"] = flushing_denormals(methods["as_saved_flush_denormal"])
    return learners, {name: on_threads(1, fn) for name, fn in methods.items()}


def learner_denormals(learner) -> int:
    """Denormal entries of the learner's Adam moments (critic and actor)."""
    return sum(denormal_count(t.numpy()) for t in adam_moments(learner.critic_optimizer) + adam_moments(learner.actor_optimizer))


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fraction", type=float, default=0.125, help="share of each moment tensor's entries made denormal")
    parser.add_argument("--calls", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--checkpoint", type=Path, default=None)
    parser.add_argument("--updates", type=int, default=400, help="TD3 updates per round on the checkpoint's state")
    parser.add_argument("--out", default="benchmarks/results/adam_denormal.json")
    args = parser.parse_args(argv)
    if not 0 < args.fraction <= 1:
        parser.error(f"--fraction: {args.fraction} (allowed: a share in (0, 1])")
    every = max(1, round(1 / args.fraction))
    optimizers = {"normal": adam_with_moments(None), "denormal": adam_with_moments(every)}
    fractions = {name: denormal_fraction(adam_moments(adam)) for name, adam in optimizers.items()}
    timed = interleaved({name: on_threads(1, adam.step) for name, adam in optimizers.items()}, args.calls, args.repeats)
    report = {
        "command": "python -m benchmarks.adam_denormal " + " ".join(argv if argv is not None else sys.argv[1:]),
        "shapes": STACKED_CRITIC_SHAPES, "threads": 1, "moments_denormal": fractions, "methods": timed,
        "denormal_over_normal": timed["denormal"]["s_per_call"] / timed["normal"]["s_per_call"],
    }
    if args.checkpoint is not None:
        report["checkpoint"] = checkpoint_denormals(args.checkpoint)
        learners, methods = run_update_methods(args.checkpoint)
        report["run_update"] = {"denormal_moments_before": {name: learner_denormals(learner) for name, learner in learners.items()}, "updates_per_round": args.updates,
                                "methods": interleaved(methods, args.updates, args.repeats)}
        saved = report["run_update"]["methods"]["as_saved"]["s_per_call"]
        report["run_update"]["over_as_saved"] = {name: m["s_per_call"] / saved for name, m in report["run_update"]["methods"].items()}
    save_report(report, args.out)
    for name, result in timed.items():
        print(f"fused Adam step, {fractions[name]:.1%} of the moments denormal: {result['s_per_call'] * 1e3:.3f} ms (median of {args.repeats} rounds)")
    print(f"denormal / normal: {report['denormal_over_normal']:.1f}x")
    if args.checkpoint is not None:
        found = report["checkpoint"]
        print(f"{found['checkpoint']}: {found['denormal_entries']} of {found['float32_entries']} float32 entries of the TD3 state denormal")
        for name, result in report["run_update"]["methods"].items():
            print(f"the run's TD3 update, {name} ({report['run_update']['denormal_moments_before'][name]} denormal moments): "
                  f"{result['s_per_call'] * 1e3:.3f} ms, {report['run_update']['over_as_saved'][name]:.3f}x as saved")
    return report


if __name__ == "__main__":
    main()
