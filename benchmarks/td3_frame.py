"""TD3 acting cost per frame at ``frames_per_batch=1`` (Algorithm 1 "act with exploration noise").

Methods, interleaved in one run (HalfCheetah-v5, the paper's actor, exploration noise 0.1):

  collector        TorchRL ``GymEnv`` + ``Collector`` (the reference path, ``implementation=reference``)
  gym_collector    :class:`~torchrl_esrl.collectors.td3_collector.GymTD3Collector` (the default)
  collector_write  the reference path plus the ``noisy`` MultiBuffer write of every frame
                   through TorchRL's ``extend`` (``direct_writes=False``)
  gym_collector_write  the default path plus the write (what ``td3_phase`` does per frame,
                   one tensor copy per key: ``direct_writes=True``)

Goal: gym_collector_write <= 0.3 ms per frame. Usage: ``python -m benchmarks.td3_frame [--quick] [--out PATH]``.
"""
from __future__ import annotations

import argparse

from benchmarks.common import interleaved, save_report  # sets OMP_WAIT_POLICY, first

import torch

from benchmarks.iteration import paper_config
from torchrl_esrl.collectors.td3_collector import GymTD3Collector, make_td3_collector
from torchrl_esrl.envs import quiet_logs
from torchrl_esrl.run.determinism import seed_everything
from torchrl_esrl.data.multibuffer import make_multibuffer
from torchrl_esrl.envs import make_train_env
from torchrl_esrl.modules.networks import make_actor_critic
from torchrl_esrl.objectives.td3 import make_td3


def run(repeats: int = 7, calls: int = 200, capacity: int = 1_000_000) -> dict:
    quiet_logs()
    cfg = paper_config()
    cfg.buffer.capacity = capacity
    seed_everything(0)
    torch.set_num_threads(cfg.td3.num_threads)  # as td3_phase acts
    methods = {}
    for name, fast in (("collector", False), ("gym_collector", True)):
        env = make_train_env(cfg)
        actor, critic = make_actor_critic(cfg, env)
        td3 = make_td3(cfg, actor, critic, env.action_spec)
        frames = iter(GymTD3Collector(env, td3, 1) if fast else make_td3_collector(env, td3, 1))
        buffer = make_multibuffer(cfg)
        buffer.direct_writes = fast  # the reference writes through TorchRL's extend
        methods[name] = lambda frames=frames: next(frames)
        methods[f"{name}_write"] = lambda frames=frames, buffer=buffer: buffer.extend(next(frames), "noisy")
    timings = interleaved(methods, calls=calls, repeats=repeats, warmup=20)
    base = timings["collector_write"]["s_per_call"]
    for t in timings.values():
        t["ms_per_frame"] = t["s_per_call"] * 1e3
        t["speedup_vs_collector_write"] = base / t["s_per_call"]
    best = timings["gym_collector_write"]["s_per_call"]
    return {"env": cfg.env.id, "capacity": capacity, "goal": "gym_collector_write <= 0.3 ms per frame",
            "met": best <= 0.3e-3, "methods": timings}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="100k-item buffers, fewer rounds")
    parser.add_argument("--out", default="benchmarks/results/td3_frame.json")
    args = parser.parse_args(argv)
    report = run(repeats=3 if args.quick else 7, calls=100 if args.quick else 200, capacity=100_000 if args.quick else 1_000_000)
    for name, t in report["methods"].items():
        print(f"{name:22s} {t['ms_per_frame']:7.3f} ms/frame  {t['speedup_vs_collector_write']:5.2f}x collector_write")
    save_report(report, args.out)
    return report


if __name__ == "__main__":
    main()
