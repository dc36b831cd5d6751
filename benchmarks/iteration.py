"""One ES-TD3Buffers iteration at the paper's settings, timed by part, and the 20-iteration run
extrapolated (figure 4).

A fraction of an iteration is measured with the recipe's own factories (conf/config.yaml, the
paper's values) and scaled by the paper's counts (Algorithm 1, Section 4.3):

  td3_env_steps   TD3 acting: TorchRL Collector, exploration policy, 1 frame per batch, writes to
                  the noisy buffer (td3_phase with no updates), per frame
  td3_updates     TD3().update(MultiBuffer.sample()), per update (buffers pre-filled to K)
  es_evaluation   ESCollector.evaluate of 120 offspring (one full episode each), per generation
  es_buffer_writes  routing a generation's transitions to good/bad (extend), per generation
  es_tell         OpenES.tell, per generation
  evaluations     the two 5-episode evaluations of the overwrite rule, per iteration

Per iteration: 100k frames x (env step + update) + 50 generations + 2 evaluations; x 20.

Each part is timed in rounds (medians). ``--compare`` also times, in the same process and
taking turns with the tuned configuration within every round, the reference configuration:
``td3.fast=false`` (stock ``TD3Loss`` + ``SoftUpdate`` + default Adam, TorchRL ``Collector``),
``td3.num_threads=null`` (the process's threads), buffer writes through TorchRL's ``extend``
(``direct_writes=False``), the whole ES population in one batch stepped on all threads, with the
forward over the flat rows on one thread (``workers=1, chunks_per_worker=1``); each part's ratio
is reported. ``--plain`` also times, interleaved with the loop's updates and sampling the same
buffer, the plain PyTorch TD3 update of ``benchmarks.td3_update`` on 1 and on 2 threads: the
update goal (>= 1.2x the best plain one) measured inside the loop.
Usage: ``python -m benchmarks.iteration [--quick] [--compare] [--plain] [--env halfcheetah] [--out PATH]``.
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path


from benchmarks.common import fill, save_report  # sets OMP_WAIT_POLICY, first

import torch
from omegaconf import OmegaConf

from torchrl_esrl.envs import quiet_logs
from torchrl_esrl.run.factories import (
    make_actor_critic, make_es, make_es_collector, make_multibuffer, make_td3, make_td3_batches, make_threshold,
    make_train_env,
)
from torchrl_esrl.collectors.mujoco_batch import MujocoBatchBackend
from torchrl_esrl.modules.networks import flat_parameters
from torchrl_esrl.run.determinism import seed_everything
from torchrl_esrl.algorithm.td3_phase import td3_phase
from torchrl_esrl.threads import torch_threads

ROOT = Path(__file__).resolve().parents[1]


def paper_config(env: str = "halfcheetah", capacity: int | None = None):
    cfg = OmegaConf.load(ROOT / "conf/config.yaml")
    cfg.env = OmegaConf.load(ROOT / f"conf/env/{env}.yaml")
    cfg.logger.progress = False
    if capacity:
        cfg.buffer.capacity = capacity
    return cfg


class Setup:
    """One configuration's components, built with the recipe's factories."""

    def __init__(self, env: str, capacity: int | None, reference: bool, td3_threads: int | None = None):
        cfg = paper_config(env, capacity)
        if reference:
            cfg.td3.fast, cfg.td3.num_threads = False, None
        elif td3_threads is not None:  # the tuned configuration with another thread count for the TD3 phase
            cfg.td3.num_threads = td3_threads
        seed_everything(0)
        self.cfg, self.reference = cfg, reference
        train_env = make_train_env(cfg)
        self.actor, critic = make_actor_critic(cfg, train_env)
        self.td3 = make_td3(cfg, self.actor, critic, train_env.action_spec)
        self.collector, self.batches = make_td3_batches(cfg, train_env, self.td3)
        self.buffer = make_multibuffer(cfg)
        self.buffer.direct_writes = not reference  # the reference writes through TorchRL's extend
        self.es, self.es_collector, self.threshold = make_es(cfg, self.actor), make_es_collector(cfg, self.actor), make_threshold(cfg)
        if reference and isinstance(self.es_collector.backend, MujocoBatchBackend):  # the whole population in lock-step
            self.es_collector.backend = MujocoBatchBackend(cfg.env.id, self.es_collector.population_actor, cfg.env.max_episode_steps, workers=1, chunks_per_worker=1)
        self.obs_dim, self.act_dim = train_env.observation_spec["observation"].shape[-1], train_env.action_spec.shape[-1]
        self.seconds: dict[str, list[float]] = {}  # part -> seconds per unit, one entry per round
        self.cpu_seconds: dict[str, list[float]] = {}  # the same in process CPU time (all threads)
        self._cpu_start = 0.0
        self.env_steps_per_generation = 0
        self.plain_seconds: dict[int, list[float]] = {}  # torch threads -> plain TD3 seconds per update, per round
        self.plain_td3: dict = {}  # torch threads -> benchmarks.td3_update.PlainTD3, built on first use

    def record(self, part: str, seconds: float, units: int) -> None:
        """Wall seconds of ``part`` per unit, and the process CPU time since the part's
        ``start_cpu`` (less inflated by other processes' load than wall time)."""
        self.seconds.setdefault(part, []).append(seconds / units)
        self.cpu_seconds.setdefault(part, []).append((time.process_time() - self._cpu_start) / units)

    def start_cpu(self) -> None:
        self._cpu_start = time.process_time()

    def env_steps(self, frames: int) -> None:
        """TD3 acting + noisy writes, no learning (good/bad still empty: the buffer is not ready)."""
        self.start_cpu()
        start = time.perf_counter()
        stats = td3_phase(frames, self.batches, self.td3, self.buffer)
        self.record("td3_env_steps", time.perf_counter() - start, stats["frames"])
        assert stats["updates"] == 0

    def generation(self) -> None:
        """One ES generation: evaluation, routing writes, tell."""
        population = self.es.ask()
        self.start_cpu()
        start = time.perf_counter()
        generation = self.es_collector.evaluate(population, mirrored=None if self.reference else self.es.mirrored())
        self.record("es_evaluation", time.perf_counter() - start, 1)
        self.env_steps_per_generation = generation.frames
        self.start_cpu()
        start = time.perf_counter()
        good = self.threshold.route(generation.returns)
        self.buffer.extend(generation.transitions[generation.member_mask(good)], "good")
        self.buffer.extend(generation.transitions[generation.member_mask(~good)], "bad")
        self.record("es_buffer_writes", time.perf_counter() - start, 1)
        self.start_cpu()
        start = time.perf_counter()
        self.es.tell(generation.returns)
        self.record("es_tell", time.perf_counter() - start, 1)

    def fill_to_ready(self) -> None:
        """Synthetic transitions where ES has not written K yet, then a few warm-up updates."""
        for name in self.buffer.names:
            missing = self.cfg.buffer.min_size - len(self.buffer[name])
            if missing > 0:
                fill(self.buffer, missing, self.obs_dim, self.act_dim, name=name)
        assert self.buffer.ready()
        with torch_threads(self.td3.num_threads):
            for _ in range(10):
                self.td3.update(self.buffer.sample())

    def updates(self, count: int) -> None:
        with torch_threads(self.td3.num_threads):  # as td3_phase runs them
            self.start_cpu()
            start = time.perf_counter()
            for _ in range(count):
                self.td3.update(self.buffer.sample())
        self.record("td3_updates", time.perf_counter() - start, count)

    def plain_updates(self, count: int, threads: int) -> None:
        """The plain PyTorch TD3 update (``benchmarks.td3_update.PlainTD3``) on ``threads`` torch
        threads, sampling this setup's buffer: the baseline of the update goal, timed inside the
        same process and rounds as the loop's own updates (not part of the iteration)."""
        from benchmarks.td3_update import PlainTD3

        plain = self.plain_td3.get(threads)
        with torch_threads(threads):
            if plain is None:
                torch.manual_seed(0)
                plain = self.plain_td3[threads] = PlainTD3(self.obs_dim, self.act_dim)
                for _ in range(10):
                    plain.update(self.buffer.sample())
            start = time.perf_counter()
            for _ in range(count):
                plain.update(self.buffer.sample())
        self.plain_seconds.setdefault(threads, []).append((time.perf_counter() - start) / count)

    def evaluations(self) -> None:
        self.start_cpu()
        start = time.perf_counter()
        self.es_collector.evaluate_policy(flat_parameters(self.actor), self.cfg.eval.episodes)
        self.es_collector.evaluate_policy(self.es.mean.detach(), self.cfg.eval.episodes)
        self.record("evaluations", time.perf_counter() - start, 1)

    def report(self) -> dict:
        cfg = self.cfg
        per = {"td3_env_steps": "frame", "es_evaluation": "generation", "es_buffer_writes": "generation", "es_tell": "generation",
               "td3_updates": "update", "evaluations": "iteration"}
        counts = {"frame": cfg.td3.frames_per_iteration, "update": cfg.td3.frames_per_iteration * cfg.td3.updates_per_frame,
                  "generation": cfg.es.generations_per_iteration, "iteration": 1}
        parts, iteration_s = {}, 0.0
        for name, rounds in self.seconds.items():
            part = {"s_per": statistics.median(rounds), "per": per[name], "rounds_s_per": rounds, "count_per_iteration": counts[per[name]],
                    "cpu_s_per": statistics.median(self.cpu_seconds[name])}
            part["s_per_iteration"] = part["s_per"] * part["count_per_iteration"]
            part["cpu_s_per_iteration"] = part["cpu_s_per"] * part["count_per_iteration"]
            iteration_s += part["s_per_iteration"]
            parts[name] = part
        parts["es_evaluation"]["env_steps_per_generation"] = self.env_steps_per_generation
        for part in parts.values():
            part["share"] = part["s_per_iteration"] / iteration_s
        run_s = iteration_s * cfg.iterations
        cpu_iteration_s = sum(p["cpu_s_per_iteration"] for p in parts.values())
        return {"cpu_iteration_s": cpu_iteration_s, "cpu_run_h": cpu_iteration_s * cfg.iterations / 3600,"env": cfg.env.id, "iterations": cfg.iterations, "parts": parts, "iteration_s": iteration_s, "run_s": run_s,
                "run_h": run_s / 3600, "goal": "20 iterations <= 4 h", "met": run_s <= 4 * 3600,
                "config": {"td3.fast": cfg.td3.fast, "td3.num_threads": cfg.td3.num_threads, "direct_writes": self.buffer.direct_writes, "es_mirrored": not self.reference,
                           "es_workers": len(getattr(self.es_collector.backend, "workers", []))}}


def run(env: str = "halfcheetah", frames: int = 2000, generations: int = 2, capacity: int | None = None,
        compare: bool = False, rounds: int = 3, td3_threads: int | None = None, plain: bool = False) -> dict:
    """Each part measured in ``rounds`` rounds (medians); with ``compare``, the reference
    configuration and the tuned one take turns within every round; with ``plain``, so does the
    plain PyTorch TD3 update on 1 and on 2 threads, sampling the tuned setup's buffer."""
    quiet_logs()
    setups = ([Setup(env, capacity, reference=True)] if compare else []) + [Setup(env, capacity, reference=False, td3_threads=td3_threads)]
    for _ in range(rounds):
        for s in setups:
            s.env_steps(max(1, frames // rounds))
    for _ in range(generations):
        for s in setups:
            s.generation()
    for s in setups:
        s.fill_to_ready()
    for _ in range(rounds):
        for s in setups:
            s.updates(max(1, frames // rounds))
        for threads in (1, 2) if plain else ():
            setups[-1].plain_updates(max(1, frames // rounds), threads)
    for s in setups:
        s.evaluations()
    for s in setups:
        s.collector.shutdown()
    report = setups[-1].report()
    report["measured"] = {"frames": frames, "updates": frames, "generations": generations, "rounds": rounds}
    if compare:
        report["reference"] = setups[0].report()
    if plain:
        seconds = {threads: statistics.median(rounds_s) for threads, rounds_s in setups[-1].plain_seconds.items()}
        ratio = min(seconds.values()) / report["parts"]["td3_updates"]["s_per"]
        report["plain_td3"] = {"s_per_update": seconds, "rounds_s_per_update": setups[-1].plain_seconds,
                               "tuned_vs_best_plain": ratio, "goal": "TD3 updates in the loop >= 1.2x the best plain PyTorch update", "met": ratio >= 1.2}
    return report


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="500 frames/updates, 1 generation")
    parser.add_argument("--env", default="halfcheetah")
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--generations", type=int, default=None)
    parser.add_argument("--compare", action="store_true", help="also time the reference configuration, interleaved, same process")
    parser.add_argument("--rounds", type=int, default=3, help="rounds per part (medians reported)")
    parser.add_argument("--td3-threads", type=int, default=None, help="td3.num_threads of the tuned configuration (default: conf/config.yaml's)")
    parser.add_argument("--plain", action="store_true", help="also time the plain PyTorch TD3 update (1 and 2 threads), interleaved with the loop's updates")
    parser.add_argument("--out", default="benchmarks/results/iteration.json")
    args = parser.parse_args(argv)
    frames, generations = args.frames or (500 if args.quick else 2000), args.generations or (1 if args.quick else 2)
    report = run(args.env, frames, generations, compare=args.compare, rounds=args.rounds, td3_threads=args.td3_threads, plain=args.plain)
    reference = report.get("reference")
    for name, p in report["parts"].items():
        ratio = f"  {reference['parts'][name]['s_per'] / p['s_per']:5.2f}x reference" if reference else ""
        print(f"{name:18s} {p['s_per'] * 1e3:10.2f} ms/{p['per']:10s} (cpu {p['cpu_s_per'] * 1e3:9.2f}) x{p['count_per_iteration']:>7g} = {p['s_per_iteration']:8.1f} s/iteration ({p['share']:5.1%}){ratio}")
    print(f"iteration {report['iteration_s']:.0f} s; {report['iterations']} iterations {report['run_h']:.2f} h (goal <= 4 h: {'met' if report['met'] else 'not met'})")
    print(f"process CPU time: iteration {report['cpu_iteration_s']:.0f} s, {report['iterations']} iterations {report['cpu_run_h']:.2f} h (core-hours; ~wall for the 1-thread TD3 parts on a quiet machine)")
    if reference:
        print(f"reference configuration: iteration {reference['iteration_s']:.0f} s, {reference['run_h']:.2f} h; tuned {reference['iteration_s'] / report['iteration_s']:.2f}x faster")
    if "plain_td3" in report:
        plain = report["plain_td3"]
        print("plain PyTorch TD3 update: " + ", ".join(f"{t} thread(s) {v * 1e3:.2f} ms" for t, v in plain["s_per_update"].items())
              + f"; the loop's updates {plain['tuned_vs_best_plain']:.2f}x the best (goal >= 1.2x: {'met' if plain['met'] else 'not met'})")
    save_report(report, args.out)
    return report


if __name__ == "__main__":
    main()
