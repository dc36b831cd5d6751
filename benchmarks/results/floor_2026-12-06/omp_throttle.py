"""The plain eager update on 2 threads (Walker2d sizes, batch 256), 100 calls after 10, timed in one process
before and after what might leave it more OpenMP threads than cores: ``peer`` builds benchmarks.peers'
TorchRL peer (which plays its prefill frames through the example's prefetching buffer), ``es`` plays
one ES generation of 120 members through the mujoco_batch backend.

Usage: PYTHONPATH=. python benchmarks/results/floor_2026-12-06/omp_throttle.py peer|es
"""
import os
import sys
import time

from benchmarks import peers
from benchmarks.common import transitions
from benchmarks.es_population import make_population
from benchmarks.iteration import paper_config
from benchmarks.td3_update import PlainTD3
from torchrl_esrl.collectors.mujoco_batch import MujocoBatchBackend
from torchrl_esrl.modules.population import PopulationActor

plain = PlainTD3(17, 6)
batch = transitions(256, 17, 6)


def speed(label: str) -> None:
    for _ in range(10):
        plain.update(batch)
    start = time.perf_counter()
    for _ in range(100):
        plain.update(batch)
    cpus = {tid: sorted(os.sched_getaffinity(int(tid))) for tid in os.listdir("/proc/self/task")}
    print(label, f"{(time.perf_counter() - start) * 10:.2f} ms", cpus, flush=True)


speed("fresh")
if sys.argv[1] == "peer":
    cfg = paper_config(peers.env_groups()["Walker2d-v5"], 10000)
    cfg.buffer.min_size = 1000
    peer = peers.TorchRLStock(cfg, 1000, 10000)
    speed("built")
    peer.frames(50)
    speed("frames")
    peer.shutdown()
    speed("shutdown")
else:
    actor, params, mirrored = make_population("Walker2d-v5", 120)
    backend = MujocoBatchBackend("Walker2d-v5", PopulationActor(actor), nthread=2)
    speed("backend built")
    backend.rollout(params, list(range(120)), mirrored)
    speed("after one generation")
