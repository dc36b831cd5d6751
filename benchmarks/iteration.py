"""One ES-TD3Buffers iteration at the paper's settings, timed by part, and the 20-iteration run
extrapolated (figure 4).

A fraction of an iteration is measured with the recipe's own factories (conf/config.yaml, the
paper's values) and scaled by the paper's counts (Algorithm 1, Section 5.3):

  td3_env_steps   TD3 acting: TorchRL Collector, exploration policy, 1 frame per batch, writes to
                  the noisy buffer (td3_phase with no updates), per frame
  td3_updates     TD3().update(MultiBuffer.sample()), per update (buffers pre-filled to K)
  es_evaluation   ESCollector.evaluate of 120 offspring (one full episode each), per generation
  es_buffer_writes  routing a generation's transitions to good/bad (extend), per generation
  es_tell         OpenES.tell, per generation
  evaluations     the two 5-episode evaluations of the overwrite rule, per iteration

Per iteration: 100k frames x (env step + update) + 50 generations + 2 evaluations; x 20.

``--compare`` times, in the same process and before the tuned run, the reference configuration:
``td3.fast=false`` (stock ``TD3Loss`` + ``SoftUpdate`` + default Adam, TorchRL ``Collector``),
``td3.num_threads=null`` (the process's threads), the ES loop without overlap; each part's ratio
is reported.
Usage: ``python -m benchmarks.iteration [--quick] [--compare] [--env halfcheetah] [--out PATH]``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import fill, save_report  # noqa: E402  (sets OMP_WAIT_POLICY)

import torch  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from torchrl_esrl.envs import quiet_logs  # noqa: E402
from torchrl_esrl.run.factories import (  # noqa: E402
    make_actor_critic, make_es, make_es_collector, make_multibuffer, make_td3, make_td3_batches, make_threshold,
    make_train_env, seed_everything,
)
from torchrl_esrl.modules.networks import flat_parameters  # noqa: E402
from torchrl_esrl.algorithm.td3_phase import td3_phase  # noqa: E402
from torchrl_esrl.threads import torch_threads  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def paper_config(env: str = "halfcheetah", capacity: int | None = None):
    cfg = OmegaConf.load(ROOT / "conf/config.yaml")
    cfg.env = OmegaConf.load(ROOT / f"conf/env/{env}.yaml")
    cfg.logger.progress = False
    if capacity:
        cfg.buffer.capacity = capacity
    return cfg


def run(env: str = "halfcheetah", frames: int = 2000, generations: int = 2, capacity: int | None = None, reference: bool = False) -> dict:
    quiet_logs()
    cfg = paper_config(env, capacity)
    if reference:
        cfg.td3.fast, cfg.td3.num_threads = False, None
    seed_everything(0)
    train_env = make_train_env(cfg)
    actor, critic = make_actor_critic(cfg, train_env)
    td3 = make_td3(cfg, actor, critic, train_env.action_spec)
    collector, batches = make_td3_batches(cfg, train_env, td3)
    buffer = make_multibuffer(cfg)
    es, es_collector, threshold = make_es(cfg, actor), make_es_collector(cfg, actor), make_threshold(cfg)
    if reference and hasattr(es_collector.backend, "overlap"):
        es_collector.backend.overlap = False
    obs_dim, act_dim = train_env.observation_spec["observation"].shape[-1], train_env.action_spec.shape[-1]
    parts = {}

    # TD3 acting + noisy writes, no learning (good/bad still empty: the buffer is not ready).
    start = time.perf_counter()
    stats = td3_phase(frames, batches, td3, buffer)
    parts["td3_env_steps"] = {"s_per": (time.perf_counter() - start) / stats["frames"], "per": "frame", "measured": stats["frames"]}
    assert stats["updates"] == 0

    # ES generations: evaluation, routing writes, tell.
    t_eval = t_write = t_tell = 0.0
    for _ in range(generations):
        population = es.ask()
        start = time.perf_counter()
        generation = es_collector.evaluate(population)
        t_eval += time.perf_counter() - start
        start = time.perf_counter()
        good = threshold.route(generation.returns)
        buffer.extend(generation.transitions[generation.member_mask(good)], "good")
        buffer.extend(generation.transitions[generation.member_mask(~good)], "bad")
        t_write += time.perf_counter() - start
        start = time.perf_counter()
        es.tell(generation.returns)
        t_tell += time.perf_counter() - start
    parts["es_evaluation"] = {"s_per": t_eval / generations, "per": "generation", "measured": generations,
                              "env_steps_per_generation": generation.frames}
    parts["es_buffer_writes"] = {"s_per": t_write / generations, "per": "generation", "measured": generations}
    parts["es_tell"] = {"s_per": t_tell / generations, "per": "generation", "measured": generations}

    # TD3 updates from three buffers holding at least K (synthetic fill where ES has not written K yet).
    for name in buffer.names:
        missing = cfg.buffer.min_size - len(buffer[name])
        if missing > 0:
            fill(buffer, missing, obs_dim, act_dim, name=name)
    assert buffer.ready()
    with torch_threads(td3.num_threads):  # as td3_phase runs them
        for _ in range(10):
            td3.update(buffer.sample())
        start = time.perf_counter()
        for _ in range(frames):
            td3.update(buffer.sample())
    parts["td3_updates"] = {"s_per": (time.perf_counter() - start) / frames, "per": "update", "measured": frames}

    start = time.perf_counter()
    es_collector.evaluate_policy(flat_parameters(actor), cfg.eval.episodes)
    es_collector.evaluate_policy(es.mean.detach(), cfg.eval.episodes)
    parts["evaluations"] = {"s_per": time.perf_counter() - start, "per": "iteration", "measured": 2}
    collector.shutdown()

    counts = {"frame": cfg.td3.frames_per_iteration, "update": cfg.td3.frames_per_iteration * cfg.td3.updates_per_frame,
              "generation": cfg.es.generations_per_iteration, "iteration": 1}
    iteration_s = 0.0
    for part in parts.values():
        part["count_per_iteration"] = counts[part["per"]]
        part["s_per_iteration"] = part["s_per"] * part["count_per_iteration"]
        iteration_s += part["s_per_iteration"]
    for part in parts.values():
        part["share"] = part["s_per_iteration"] / iteration_s
    run_s = iteration_s * cfg.iterations
    return {"env": cfg.env.id, "iterations": cfg.iterations, "parts": parts, "iteration_s": iteration_s, "run_s": run_s,
            "run_h": run_s / 3600, "goal": "20 iterations <= 4 h", "met": run_s <= 4 * 3600,
            "measured": {"frames": frames, "updates": frames, "generations": generations}}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="500 frames/updates, 1 generation")
    parser.add_argument("--env", default="halfcheetah")
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--generations", type=int, default=None)
    parser.add_argument("--compare", action="store_true", help="also time the reference configuration first, same process")
    parser.add_argument("--out", default="benchmarks/results/iteration.json")
    args = parser.parse_args(argv)
    frames, generations = args.frames or (500 if args.quick else 2000), args.generations or (1 if args.quick else 2)
    reference = run(args.env, frames, generations, reference=True) if args.compare else None
    report = run(args.env, frames, generations)
    for name, p in report["parts"].items():
        ratio = f"  {reference['parts'][name]['s_per'] / p['s_per']:5.2f}x reference" if reference else ""
        print(f"{name:18s} {p['s_per'] * 1e3:10.2f} ms/{p['per']:10s} x{p['count_per_iteration']:>7g} = {p['s_per_iteration']:8.1f} s/iteration ({p['share']:5.1%}){ratio}")
    print(f"iteration {report['iteration_s']:.0f} s; {report['iterations']} iterations {report['run_h']:.2f} h (goal <= 4 h: {'met' if report['met'] else 'not met'})")
    if reference:
        print(f"reference configuration: iteration {reference['iteration_s']:.0f} s, {reference['run_h']:.2f} h; tuned {reference['iteration_s'] / report['iteration_s']:.2f}x faster")
        report["reference"] = reference
    save_report(report, args.out)
    return report


if __name__ == "__main__":
    main()
