import time, os, torch
from benchmarks import peers
from benchmarks.iteration import paper_config
from benchmarks.td3_update import PlainTD3
from benchmarks.common import transitions
obs, act = 17, 6
plain = PlainTD3(obs, act)
batch = transitions(256, obs, act)
def speed(label):
    for _ in range(10): plain.update(batch)
    t = time.perf_counter()
    for _ in range(100): plain.update(batch)
    aff = {tid: sorted(os.sched_getaffinity(int(tid))) for tid in os.listdir("/proc/self/task")}
    print(label, f"{(time.perf_counter()-t)*10:.2f} ms", aff, flush=True)
cfg = paper_config(peers.env_groups()["Walker2d-v5"], 10000); cfg.buffer.min_size = 1000
speed("fresh")
ts = peers.TorchRLStock(cfg, 1000, 10000)
speed("built")
ts.frames(50)
speed("frames")
ts.shutdown()
speed("shutdown")
