"""Where the loop's TD3 update spends its time, op by op: ``torch.profiler`` over the update of
``make_td3``'s fast pieces (Walker2d-v5 sizes, batch 256, three 100k-item buffers), on 1 and 2
threads, beside the plain per-update time of the same object.

Usage (recipes held): ``PYTHONPATH=. python benchmarks/results/floor_2026-12-06/update_profile.py``; record
``update_profile.txt``.
Prints, per thread count: ms per update unprofiled, op calls per update, and the self time of each
op as a share of the profiled total, matrix products (``addmm``, ``baddbmm``, ``bmm``, ``mm``) first.
"""
import os
import time

from benchmarks.common import SHAPES, fill

import torch
from torch.profiler import ProfilerActivity, profile
from torchrl.data import Bounded

from benchmarks.td3_update import FAST_TD3
from torchrl_esrl.data.multibuffer import MultiBuffer
from torchrl_esrl.modules.networks import make_actor, make_critic
from torchrl_esrl.objectives.td3 import TD3

PRODUCTS = ("aten::addmm", "aten::baddbmm", "aten::bmm", "aten::mm")
UPDATES = 200

obs_dim, act_dim = SHAPES["Walker2d-v5"]
buffer = MultiBuffer(ratio=(0.5, 0.2, 0.3), capacity=100_000, batch_size=256, direct_reads=True)
for name in buffer.names:
    fill(buffer, 100_000, obs_dim, act_dim, name=name)
spec = Bounded(-torch.ones(act_dim), torch.ones(act_dim), shape=(act_dim,))
torch.manual_seed(0)
td3 = TD3(make_actor(obs_dim, spec), make_critic(obs_dim, act_dim), spec, **FAST_TD3)
print(f"load before: {os.getloadavg()[0]:.2f}")
for threads in (1, 2):
    torch.set_num_threads(threads)
    for _ in range(50):
        td3.update(buffer.sample())
    start = time.perf_counter()
    for _ in range(UPDATES):
        td3.update(buffer.sample())
    per_update = (time.perf_counter() - start) / UPDATES * 1e3
    start = time.perf_counter()
    for _ in range(UPDATES):
        buffer.sample()
    per_sample = (time.perf_counter() - start) / UPDATES * 1e3
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(UPDATES):
            td3.update(buffer.sample())
    events = [e for e in prof.key_averages() if e.self_cpu_time_total > 0]
    total = sum(e.self_cpu_time_total for e in events)
    calls = sum(e.count for e in events if e.key.startswith("aten::")) / UPDATES
    products = sum(e.self_cpu_time_total for e in events if e.key in PRODUCTS)
    print(f"\n{threads} thread(s): {per_update:.3f} ms an update (its batch's sampling {per_sample:.3f} ms), "
          f"{total / UPDATES / 1e3:.3f} ms profiled, {calls:.0f} aten op calls an update; "
          f"matrix products {products / total:.1%} of the profiled self time")
    for event in sorted(events, key=lambda e: -e.self_cpu_time_total)[:25]:
        print(f"  {event.key:32s} {event.self_cpu_time_total / total:6.1%}  {event.count / UPDATES:5.1f} calls  "
              f"{event.self_cpu_time_total / event.count:8.1f} us a call")
print(f"\nload after: {os.getloadavg()[0]:.2f}; torch {torch.__version__}")
