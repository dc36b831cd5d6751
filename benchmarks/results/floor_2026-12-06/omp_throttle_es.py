import time, os, torch
from benchmarks.es_population import make_population
from benchmarks.td3_update import PlainTD3
from benchmarks.common import transitions
from torchrl_esrl.collectors.mujoco_batch import MujocoBatchBackend
from torchrl_esrl.modules.population import PopulationActor
obs, act = 17, 6
plain = PlainTD3(obs, act)
batch = transitions(256, obs, act)
def speed(label):
    for _ in range(10): plain.update(batch)
    t = time.perf_counter()
    for _ in range(100): plain.update(batch)
    print(label, f"{(time.perf_counter()-t)*10:.2f} ms; threads", len(os.listdir("/proc/self/task")), flush=True)
speed("fresh")
actor, params, mirrored = make_population("Walker2d-v5", 120)
backend = MujocoBatchBackend("Walker2d-v5", PopulationActor(actor), nthread=2)
speed("backend built")
gen = backend.rollout(params, list(range(120)), mirrored)
speed("after one generation")
