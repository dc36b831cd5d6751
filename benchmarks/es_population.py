"""ES population evaluation throughput: env-steps/s of one generation of full episodes.

120 offspring of the paper's 2x256 tanh actor (an OpenAI-ES population: 60 mirrored pairs of
sigma 0.005 perturbations of a random actor), one episode each (up to 1000 steps), measured in
one run for:

  batched    the ``mujoco_batch`` backend as the ES phase runs it (two workers, each playing chunks
             of mirrored pairs on a mujoco.batch.Batch of its own, one batched forward per chunk
             and step)
  batched_rows  the same with the forward over the flat rows
  one_batch  one chunk: the whole population in one batch stepped on all MuJoCo threads,
             the forward over the mirrored pairs on one thread (``workers=1, chunks_per_worker=1``)
  raw        the same mujoco.batch stepping with fixed controls, every member for every step: no
             policy, no rewards, no termination
  raw_replay the same mujoco.batch stepping replaying the batched run's own episodes: each member's
             recorded actions, until its recorded length (physics of the very trajectories the
             evaluation played, the ceiling for it; ``raw`` steps other states, with other contacts,
             and never stops early)
  chunks_of_N_pairs  (``--chunk-sweep N ...``) the batched backend with chunks of about N pairs each:
             smaller chunks keep a chunk's offsets in a core's cache, larger ones pay the per-step
             bookkeeping fewer times; the record says whether they played the batched run's
             episodes bit for bit
  serial     one gymnasium env, offspring after offspring, torch forward per step with the
             offspring's weights loaded into an actor
  lockstep   the reference ``gym`` backend (P gymnasium envs, one batched forward per step)

Usage: ``python -m benchmarks.es_population [--quick] [--sweep] [--chunk-sweep PAIRS ...] [--out PATH]``.
Each run records wall-clock steps/s and the process's CPU time per step (``cpu_us_per_step``; the
printed ``cpu: raw/it`` is raw's over the method's): on a machine shared with other work, compare
variants by the latter, within one run.

OpenMP threads that spin after a torch forward steal the cores MuJoCo's batch threads need next.
``OMP_WAIT_POLICY`` is read when torch loads, so it is set here, before the import, unless the
caller set it; the JSON records it.
"""
from __future__ import annotations

import argparse
import json
import os

if os.environ.get("BENCHMARKS_OMP_PASSIVE"):  # 1: OMP_WAIT_POLICY=PASSIVE; default: libgomp's own policy, as the recipes run
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
import sys
import time
from pathlib import Path


import gymnasium as gym
import mujoco
import mujoco.batch
import numpy as np
import torch
from torchrl.data import Bounded

from benchmarks.common import machine
from torchrl_esrl.collectors.gym_backend import GymBackend
from torchrl_esrl.collectors.mujoco_batch import MujocoBatchBackend
from torchrl_esrl.es.openes import OpenES
from torchrl_esrl.modules.networks import flat_parameters, load_flat_parameters, make_actor
from torchrl_esrl.modules.population import PopulationActor

ENVS = ["HalfCheetah-v5", "Walker2d-v5"]


def make_population(env_id: str, members: int, sigma: float = 0.005, seed: int = 0):
    """A random actor and an OpenAI-ES population around it: ``(actor, params, mirrored)``."""
    env = gym.make(env_id)
    torch.manual_seed(seed)
    low, high = torch.as_tensor(env.action_space.low), torch.as_tensor(env.action_space.high)
    actor = make_actor(env.observation_space.shape[0], Bounded(low, high, shape=low.shape))
    es = OpenES(flat_parameters(actor), population_size=members, sigma=sigma, generator=torch.Generator().manual_seed(seed))
    params = es.ask().contiguous()
    return actor, params, es.mirrored(params)


def timed(steps: int, seconds: float, cpu_seconds: float) -> dict:
    """A run's figures: wall-clock steps/s, and this process's CPU time per step (threads that wait
    cost none of it, so it moves less than wall time on a machine shared with other work)."""
    return {"steps": steps, "seconds": seconds, "steps_per_s": steps / seconds, "cpu_us_per_step": 1e6 * cpu_seconds / steps}


def time_backend(backend, params, seeds, mirrored=None) -> dict:
    start, cpu = time.perf_counter(), time.process_time()
    generation = backend.rollout(params, seeds, mirrored=mirrored)
    seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - cpu
    return timed(generation.frames, seconds, cpu_seconds) | {
        "mean_return": float(generation.returns.mean()), "mean_length": float(generation.lengths.float().mean())}


def initial_batch(env, seeds, nthread: int) -> mujoco.batch.Batch:
    """A mujoco.batch of ``env``'s model, one simulation per seed, each in gymnasium's initial state
    for that seed."""
    batch = mujoco.batch.Batch(env.model, len(seeds), nthread)
    row = np.empty(batch.nstate)
    for p, seed in enumerate(seeds):
        env.reset(seed=int(seed))
        mujoco.mj_getState(env.model, env.data, row, mujoco.mjtState.mjSTATE_INTEGRATION)
        batch.state[p] = row
    return batch


def time_raw_physics(env_id: str, members: int, steps: int, seeds, nthread: int) -> dict:
    """mujoco.batch stepping alone: gymnasium's initial states, fixed random controls, every member for ``steps``."""
    env = gym.make(env_id).unwrapped
    batch = initial_batch(env, seeds, nthread)
    rng = np.random.default_rng(0)
    batch.bind("ctrl")[:] = rng.uniform(-0.5, 0.5, (members, env.model.nu))
    start, cpu = time.perf_counter(), time.process_time()
    for _ in range(steps):
        batch.step(nstep=env.frame_skip)
    return timed(members * steps, time.perf_counter() - start, time.process_time() - cpu)


def time_raw_replay(env_id: str, generation, seeds, nthread: int) -> dict:
    """mujoco.batch stepping alone, replaying ``generation`` (:func:`replay`)."""
    _, seconds, cpu_seconds = replay(env_id, generation, seeds, nthread)
    return timed(int(generation.lengths.sum()), seconds, cpu_seconds)


def replay(env_id: str, generation, seeds, nthread: int) -> tuple[mujoco.batch.Batch, float, float]:
    """Steps ``generation``'s episodes again on one mujoco.batch: gymnasium's initial states, then
    each member's recorded actions, the live members only, until each one's recorded length. The
    batch as it ends (each member in its last state), and the wall and CPU seconds of the stepping."""
    env = gym.make(env_id).unwrapped
    members = len(seeds)
    lengths = generation.lengths.numpy()
    member_of = generation.transitions.get(("collector", "traj_ids")).numpy()
    step_of = np.arange(len(member_of)) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    actions = np.zeros((members, int(lengths.max()), env.model.nu))
    actions[member_of, step_of] = generation.transitions.get("action").numpy()
    batch = initial_batch(env, seeds, nthread)
    ctrl = batch.bind("ctrl")
    start, cpu = time.perf_counter(), time.process_time()
    for t in range(int(lengths.max())):
        live = np.flatnonzero(lengths > t)
        ctrl[live] = actions[live, t]
        batch.step(ids=None if len(live) == members else live, nstep=env.frame_skip)
    return batch, time.perf_counter() - start, time.process_time() - cpu


@torch.no_grad()
def time_serial(env_id: str, actor, params, seeds, steps: int) -> dict:
    """The plain way: one env, one offspring after another, a torch forward per step."""
    env = gym.make(env_id, max_episode_steps=steps)
    mlp = actor[0].module
    low, high = actor[1].action_low, actor[1].action_high
    total = 0
    start, cpu = time.perf_counter(), time.process_time()
    for p, seed in enumerate(seeds):
        load_flat_parameters(actor, params[p])
        obs, _ = env.reset(seed=int(seed))
        while True:
            x = torch.as_tensor(obs, dtype=torch.float32)
            action = (low + (high - low) * (mlp(x).tanh() + 1) / 2).numpy()
            obs, _, term, trunc, _ = env.step(action)
            total += 1
            if term or trunc:
                break
    return timed(total, time.perf_counter() - start, time.process_time() - cpu)


def interleaved_runs(repeats: int, measures: dict) -> dict:
    """Every method once per round, ``repeats`` rounds (the machine may be shared): the median
    run of each, with every run's steps/s kept."""
    runs = {name: [] for name in measures}
    for _ in range(repeats):
        for name, measure in measures.items():
            runs[name].append(measure())
    out = {}
    for name, rs in runs.items():
        ordered = sorted(rs, key=lambda r: r["steps_per_s"])
        out[name] = ordered[len(ordered) // 2] | {"runs_steps_per_s": [round(r["steps_per_s"]) for r in rs]}
    return out


def chunked_backend(env_id: str, policy, steps: int, nthread: int, pairs: int, members: int) -> MujocoBatchBackend:
    """The batched backend with its two workers playing chunks of about ``pairs`` mirrored pairs."""
    backend = MujocoBatchBackend(env_id, policy, max_episode_steps=steps, nthread=nthread, min_chunk=1)
    backend.chunks_per_worker = max(1, -(-(members // 2) // pairs) // len(backend.workers))
    return backend


def run(env_id: str, members: int, steps: int, nthread: int, sweep: bool, repeats: int = 1, skip_slow: bool = False,
        chunk_pairs: tuple[int, ...] = ()) -> dict:
    actor, params, mirrored = make_population(env_id, members)
    policy = PopulationActor(actor)
    seeds = list(range(1000, 1000 + members))
    batched_backend = MujocoBatchBackend(env_id, policy, max_episode_steps=steps, nthread=nthread)
    one_batch_backend = MujocoBatchBackend(env_id, policy, max_episode_steps=steps, nthread=nthread, workers=1, chunks_per_worker=1)
    batched_backend.rollout(params[:2], seeds[:2])  # warm-up (imports, allocator)
    one_batch_backend.rollout(params[:2], seeds[:2])
    lockstep_backend = GymBackend(env_id, policy, max_episode_steps=steps)
    played = batched_backend.rollout(params, seeds, mirrored)  # the episodes raw_replay steps again
    measures = {
        "batched": lambda: time_backend(batched_backend, params, seeds, mirrored),
        "batched_rows": lambda: time_backend(batched_backend, params, seeds),
        "one_batch": lambda: time_backend(one_batch_backend, params, seeds, mirrored),
        "raw": lambda: time_raw_physics(env_id, members, steps, seeds, nthread),
        "raw_replay": lambda: time_raw_replay(env_id, played, seeds, nthread),
    }
    chunked = {pairs: chunked_backend(env_id, policy, steps, nthread, pairs, members) for pairs in chunk_pairs}
    for pairs, backend in chunked.items():
        measures[f"chunks_of_{pairs}_pairs"] = lambda backend=backend: time_backend(backend, params, seeds, mirrored)
    if not skip_slow:
        measures["serial"] = lambda: time_serial(env_id, actor, params, seeds, steps)
        measures["lockstep"] = lambda: time_backend(lockstep_backend, params, seeds)
    results = interleaved_runs(repeats, measures)
    for pairs, backend in chunked.items():  # every member's arithmetic is its own: any chunking plays the same episodes
        generation = backend.rollout(params, seeds, mirrored)
        results[f"chunks_of_{pairs}_pairs"] |= {
            "chunk_members": [len(chunk.members) for chunk in backend.chunks(members, mirrored)],
            "same_episodes_as_batched": bool(torch.equal(generation.returns, played.returns) and torch.equal(
                generation.transitions.get("action"), played.transitions.get("action")))}
    if sweep:
        variants = {}
        for workers in (1, 2):
            for chunks in (1, 2, 4):
                backend = MujocoBatchBackend(env_id, policy, max_episode_steps=steps, nthread=nthread, workers=workers, chunks_per_worker=chunks)
                variants[f"workers{workers}_chunks{chunks}"] = time_backend(backend, params, seeds, mirrored)
        backend = MujocoBatchBackend(env_id, policy, max_episode_steps=steps, nthread=nthread, persistent=True)
        variants["persistent"] = time_backend(backend, params, seeds, mirrored)
        results["sweep"] = variants
    return results


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="smoke run: 16 members x 200 steps")
    parser.add_argument("--members", type=int, default=None)
    parser.add_argument("--steps", type=int, default=None)
    parser.add_argument("--nthread", type=int, default=os.cpu_count() or 1, help="threads of the backend and of the raw physics batch")
    parser.add_argument("--torch-threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    parser.add_argument("--sweep", action="store_true", help="also time workers x chunks and persistent-batch variants")
    parser.add_argument("--chunk-sweep", type=int, nargs="+", default=[], metavar="PAIRS",
                        help="also time the batched backend with chunks of about PAIRS mirrored pairs each, in the same rounds")
    parser.add_argument("--envs", nargs="+", default=ENVS)
    parser.add_argument("--repeats", type=int, default=3, help="interleaved rounds; each method's median run is reported")
    parser.add_argument("--skip-slow", action="store_true", help="leave out the serial and lockstep gymnasium loops")
    parser.add_argument("--out", default="benchmarks/results/es_population.json")
    args = parser.parse_args(argv)
    members = args.members or (16 if args.quick else 120)
    steps = args.steps or (200 if args.quick else 1000)
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    report = {
        "machine": {**machine(), "mujoco": mujoco.__version__, "gymnasium": gym.__version__, "mujoco_threads": args.nthread},
        "members": members, "max_episode_steps": steps, "sigma": 0.005, "actor": "2x256 tanh",
        "command": " ".join(["python -m benchmarks.es_population", *(argv if argv is not None else sys.argv[1:])]),
        "load_average_before": os.getloadavg(),
        "envs": {},
    }
    header = (f"{'env':16s} {'method':22s} {'steps':>8s} {'seconds':>8s} {'steps/s':>9s} {'vs raw':>7s} {'vs replay':>9s} {'vs serial':>9s}"
              f" {'cpu us/step':>11s} {'cpu: raw/it':>11s}")
    print(header)
    for env_id in args.envs:
        results = run(env_id, members, steps, args.nthread, args.sweep, args.repeats, args.skip_slow, tuple(args.chunk_sweep))
        raw, replay = results["raw"]["steps_per_s"], results["raw_replay"]["steps_per_s"]
        serial = results["serial"]["steps_per_s"] if "serial" in results else float("nan")
        rows = {k: v for k, v in results.items() if k != "sweep"} | {f"sweep:{k}": v for k, v in results.get("sweep", {}).items()}
        for method, r in rows.items():
            r["vs_raw"], r["vs_raw_replay"], r["vs_serial"] = r["steps_per_s"] / raw, r["steps_per_s"] / replay, r["steps_per_s"] / serial
            r["cpu_raw_over_this"] = results["raw"]["cpu_us_per_step"] / r["cpu_us_per_step"]
            print(f"{env_id:16s} {method:22s} {r['steps']:8d} {r['seconds']:8.2f} {r['steps_per_s']:9.0f} "
                  f"{r['vs_raw']:7.2f} {r['vs_raw_replay']:9.2f} {r['vs_serial']:9.2f} {r['cpu_us_per_step']:11.1f} {r['cpu_raw_over_this']:11.2f}")
        report["envs"][env_id] = results
    report["load_average_after"] = os.getloadavg()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2))
    print(f"wrote {out}")
    return report


if __name__ == "__main__":
    main()
