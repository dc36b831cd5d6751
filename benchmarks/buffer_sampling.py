"""MultiBuffer ratio sampling vs one TorchRL replay buffer.

  baseline    one ``TensorDictReplayBuffer`` (``LazyTensorStorage``, uniform) ``sample(256)`` from
              a full buffer of ``capacity`` HalfCheetah-shaped transitions
  multibuffer ``MultiBuffer.sample()``: 256 at 0.5:0.2:0.3 (128/51/77) from three full buffers
              (``ExactRatioSampler`` asks each buffer's ``RandomSampler`` for its count, then
              ``ExactRatioStorage.get`` copies one ``index_select`` per key and buffer into one batch)
  naive       three ``TensorDictReplayBuffer.sample(n)`` calls + ``torch.cat`` (+ the source tag)
  torchrl_ensemble  TorchRL's stock ``ReplayBufferEnsemble(sample_from_all=True)`` over the same three
              buffers, 255 items (85 each: it can only split evenly), stacked as [3, 85]: what the
              MultiBuffer would cost built from TorchRL's ensemble as is (and without exact ratios)

Goal: multibuffer <= 1.2x baseline.
Usage: ``python -m benchmarks.buffer_sampling [--quick] [--out PATH]``.
"""
from __future__ import annotations

import argparse


from benchmarks.common import SHAPES, fill, interleaved, save_report  # sets OMP_WAIT_POLICY, first

import torch

from torchrl.data import ReplayBufferEnsemble

from torchrl_esrl.data.multibuffer import MultiBuffer, make_buffer


def run(capacity: int = 1_000_000, batch_size: int = 256, ratio=(0.5, 0.2, 0.3), repeats: int = 7, calls: int = 300, env_id: str = "HalfCheetah-v5") -> dict:
    obs_dim, act_dim = SHAPES[env_id]
    single = make_buffer(capacity)
    fill(single, capacity, obs_dim, act_dim)
    multi = MultiBuffer(ratio=ratio, capacity=capacity, batch_size=batch_size)
    for name in multi.names:
        fill(multi, capacity, obs_dim, act_dim, name=name)
    assert multi.storage.fast_path()
    counts = multi.counts()

    def naive():
        parts = [multi.buffers[n].sample(c) for n, c in counts.items() if c]
        batch = torch.cat(parts, 0)
        batch.set("buffer", torch.repeat_interleave(torch.arange(3), torch.tensor(list(counts.values()))))
        return batch

    stock = ReplayBufferEnsemble(*(multi.buffers[n] for n in multi.names), sample_from_all=True)
    stock_batch = 3 * (batch_size // 3)

    timings = interleaved(
        {"baseline": lambda: single.sample(batch_size), "multibuffer": multi.sample, "naive": naive,
         "torchrl_ensemble": lambda: stock.sample(stock_batch)},
        calls=calls, repeats=repeats,
    )
    base = timings["baseline"]["s_per_call"]
    for t in timings.values():
        t["ratio"] = t["s_per_call"] / base
        t["ratio_best"] = t["best_s_per_call"] / timings["baseline"]["best_s_per_call"]  # quietest rounds
    return {"env": env_id, "capacity": capacity, "batch_size": batch_size, "ratio": list(ratio), "counts": counts,
            "goal": "multibuffer <= 1.2x baseline", "met": timings["multibuffer"]["ratio"] <= 1.2, "methods": timings}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="100k-item buffers, fewer repetitions")
    parser.add_argument("--capacity", type=int, default=None)
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--out", default="benchmarks/results/buffer_sampling.json")
    args = parser.parse_args(argv)
    capacity = args.capacity or (100_000 if args.quick else 1_000_000)
    report = run(capacity, repeats=args.repeats or (3 if args.quick else 7), calls=100 if args.quick else 300)
    for name, t in report["methods"].items():
        print(f"{name:16s} {t['s_per_call'] * 1e6:8.1f} us  {t['ratio']:5.2f}x (best rounds {t['ratio_best']:5.2f}x)")
    save_report(report, args.out)
    print(f"load average {report['machine']['load_average']}")
    return report


if __name__ == "__main__":
    main()
