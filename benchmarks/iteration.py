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
taking turns with the fast configuration within every round, ``implementation=reference`` (stock
TorchRL end to end, ``torchrl_esrl/run/implementation.py``); each part's ratio is reported.
``--ablation`` switches each fast piece (``FAST_PIECES``) back to its reference alone,
the rest fast, and times the parts that piece touches in the same interleaved rounds as the fast
configuration; each piece's saving is reported as its share of the fast paper-size iteration
(``ablation`` in the JSON record; docs/performance.md's table). ``--plain`` also times,
interleaved with the loop's updates and sampling the same buffer, the plain PyTorch TD3 update of
``benchmarks.td3_update`` on 1 and on 2 threads: the update goal (>= 1.2x the best plain one)
measured inside the loop.
Usage: ``python -m benchmarks.iteration [--quick] [--compare] [--ablation] [--plain] [--env halfcheetah] [--capacity N] [--out PATH]``.
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path


from benchmarks.common import fill, save_report  # sets OMP_WAIT_POLICY, first
from hydra import compose, initialize_config_dir

import torch

from torchrl_esrl.envs import quiet_logs
from torchrl_esrl.collectors.es_collector import make_es_collector
from torchrl_esrl.collectors.td3_collector import make_frame_batches
from torchrl_esrl.data.multibuffer import make_multibuffer
from torchrl_esrl.data.threshold import make_threshold
from torchrl_esrl.envs import make_train_env
from torchrl_esrl.es.openes import make_es
from torchrl_esrl.modules.networks import flat_parameters, make_actor_critic
from torchrl_esrl.objectives.td3 import make_td3
from torchrl_esrl.run.algorithm_info import load_recipe
from torchrl_esrl.run.implementation import FAST_PIECES
from torchrl_esrl.run.determinism import seed_everything
from torchrl_esrl.algorithm.td3_phase import td3_phase
from torchrl_esrl.threads import torch_threads

ROOT = Path(__file__).resolve().parents[1]
PARTS = ("td3_env_steps", "es_evaluation", "es_buffer_writes", "es_tell", "td3_updates", "evaluations")
# The parts of an iteration each fast piece takes part in: what its ablation times.
PIECE_PARTS = {
    "td3_loss": ("td3_updates",),
    "soft_update": ("td3_updates",),
    "adam": ("td3_updates",),
    "buffer_reads": ("td3_updates",),
    "td3_collector": ("td3_env_steps",),
    "buffer_writes": ("td3_env_steps", "es_buffer_writes"),
    "es_forward": ("es_evaluation", "evaluations"),
    "es_physics": ("es_evaluation", "evaluations"),
}
assert set(PIECE_PARTS) == set(FAST_PIECES), "every fast piece has its parts"


def paper_config(env: str = "halfcheetah", capacity: int | None = None, max_episode_steps: int | None = None):
    """conf/config.yaml's paper values; ``capacity`` (and K with it, if smaller) and
    ``max_episode_steps`` shrink a smoke run."""
    load_recipe(ROOT / "recipes" / "es_td3.py")  # registers conf/config.yaml's schema (recipe_main), which the config lists first
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=[f"env={env}", "logger.progress=false"])
    if capacity:
        cfg.buffer.capacity = capacity
        cfg.buffer.min_size = min(cfg.buffer.min_size, capacity)
    if max_episode_steps:
        cfg.env.max_episode_steps = max_episode_steps
    return cfg


class Setup:
    """One configuration's components, built with the recipe's factories from ``pieces`` (the
    fast pieces it uses); ``parts`` are the parts of an iteration it is timed on."""

    def __init__(self, env: str, capacity: int | None, pieces, td3_threads: int | None = None, parts=PARTS, name: str = "fast", max_episode_steps: int | None = None):
        cfg = paper_config(env, capacity, max_episode_steps)
        if td3_threads is not None:  # another thread count for the TD3 phase
            cfg.td3.num_threads = td3_threads
        seed_everything(0)
        self.cfg, self.pieces, self.parts, self.name = cfg, frozenset(pieces), tuple(parts), name
        train_env = make_train_env(cfg)
        self.actor, critic = make_actor_critic(cfg, train_env)
        self.td3 = make_td3(cfg, self.actor, critic, train_env.action_spec, pieces=self.pieces)
        self.collector, self.batches = make_frame_batches(cfg, train_env, self.td3, pieces=self.pieces)
        self.buffer = make_multibuffer(cfg, pieces=self.pieces)
        self.es, self.es_collector, self.threshold = make_es(cfg, self.actor), make_es_collector(cfg, self.actor, pieces=self.pieces), make_threshold(cfg)
        self.obs_dim, self.act_dim = train_env.observation_spec["observation"].shape[-1], train_env.action_spec.shape[-1]
        self.seconds: dict[str, list[float]] = {}  # part -> seconds per unit, one entry per round
        self.cpu_seconds: dict[str, list[float]] = {}  # the same in process CPU time (all threads)
        self._cpu_start = 0.0
        self.env_steps_per_generation = 0
        self.plain_seconds: dict[int, list[float]] = {}  # torch threads -> plain TD3 seconds per update, per round
        self.plain_td3: dict = {}  # torch threads -> benchmarks.td3_update.PlainTD3, built on first use

    def times(self, *parts: str) -> bool:
        return any(part in self.parts for part in parts)

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
        generation = self.es_collector.evaluate(population, mirrored=self.es.mirrored(population))  # the ES phase's call
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
        self.es.tell(population, generation.returns)
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
        if "es_evaluation" in parts:
            parts["es_evaluation"]["env_steps_per_generation"] = self.env_steps_per_generation
        for part in parts.values():
            part["share"] = part["s_per_iteration"] / iteration_s if iteration_s else 0.0
        run_s = iteration_s * cfg.iterations
        cpu_iteration_s = sum(p["cpu_s_per_iteration"] for p in parts.values())
        return {"cpu_iteration_s": cpu_iteration_s, "cpu_run_h": cpu_iteration_s * cfg.iterations / 3600,"env": cfg.env.id, "iterations": cfg.iterations, "parts": parts, "iteration_s": iteration_s, "run_s": run_s,
                "run_h": run_s / 3600, "goal": "20 iterations <= 4 h", "met": run_s <= 4 * 3600,
                "config": {"fast_pieces": sorted(self.pieces), "td3.num_threads": cfg.td3.num_threads, "es_backend": self.es_collector.backend.name,
                           "es_population": type(self.es_collector.population_actor).__name__, "es_workers": len(getattr(self.es_collector.backend, "workers", []))}}


def run(env: str = "halfcheetah", frames: int = 2000, generations: int = 2, capacity: int | None = None,
        compare: bool = False, rounds: int = 3, td3_threads: int | None = None, plain: bool = False, ablation: bool = False,
        max_episode_steps: int | None = None) -> dict:
    """Each part measured in ``rounds`` rounds (medians). The fast configuration and, with
    ``compare``, the reference, with ``ablation``, each fast piece switched back alone (timed on
    the parts it touches), take turns within every round; with ``plain``, so does the plain
    PyTorch TD3 update on 1 and on 2 threads, sampling the fast setup's buffer."""
    quiet_logs()
    fast = Setup(env, capacity, FAST_PIECES, td3_threads, max_episode_steps=max_episode_steps)
    setups = ([Setup(env, capacity, (), td3_threads, name="reference", max_episode_steps=max_episode_steps)] if compare else []) + [fast]
    ablated = {
        piece: Setup(env, capacity, set(FAST_PIECES) - {piece}, td3_threads, PIECE_PARTS[piece], name=f"without {piece}", max_episode_steps=max_episode_steps)
        for piece in (FAST_PIECES if ablation else ())
    }
    setups += list(ablated.values())
    for _ in range(rounds):
        for s in setups:
            if s.times("td3_env_steps"):
                s.env_steps(max(1, frames // rounds))
    for _ in range(generations):
        for s in setups:
            if s.times("es_evaluation", "es_buffer_writes", "es_tell"):
                s.generation()
    updating = [s for s in setups if s.times("td3_updates")]
    for s in updating:
        s.fill_to_ready()
    for _ in range(rounds):
        for s in updating:
            s.updates(max(1, frames // rounds))
        for threads in (1, 2) if plain else ():
            fast.plain_updates(max(1, frames // rounds), threads)
    for s in setups:
        if s.times("evaluations"):
            s.evaluations()
    for s in setups:
        s.collector.shutdown()
    report = fast.report()
    report["measured"] = {"frames": frames, "updates": frames, "generations": generations, "rounds": rounds}
    if compare:
        report["reference"] = setups[0].report()
    if ablation:
        report["ablation"] = ablation_report(fast, ablated)
    if plain:
        seconds = {threads: statistics.median(rounds_s) for threads, rounds_s in fast.plain_seconds.items()}
        ratio = min(seconds.values()) / report["parts"]["td3_updates"]["s_per"]
        report["plain_td3"] = {"s_per_update": seconds, "rounds_s_per_update": fast.plain_seconds,
                               "tuned_vs_best_plain": ratio, "goal": "TD3 updates in the loop >= 1.2x the best plain PyTorch update", "met": ratio >= 1.2}
    return report


def ablation_report(fast: Setup, ablated: dict[str, Setup]) -> dict:
    """Per fast piece: the iteration with that piece switched back to its reference (its parts
    timed, the other parts the fast configuration's), the seconds it saves, and their share of
    the fast iteration."""
    fast_report = fast.report()
    fast_parts, fast_iteration = fast_report["parts"], fast_report["iteration_s"]
    out = {}
    for piece, setup in ablated.items():
        parts = setup.report()["parts"]
        iteration_s = fast_iteration + sum(parts[p]["s_per_iteration"] - fast_parts[p]["s_per_iteration"] for p in setup.parts)
        saved = iteration_s - fast_iteration
        out[piece] = {
            "reference": FAST_PIECES[piece], "parts_timed": list(setup.parts),
            "parts": {p: {"fast_s_per_iteration": fast_parts[p]["s_per_iteration"], "reference_s_per_iteration": parts[p]["s_per_iteration"],
                          "fast_rounds_s_per": fast_parts[p]["rounds_s_per"], "reference_rounds_s_per": parts[p]["rounds_s_per"]} for p in setup.parts},
            "iteration_s": iteration_s, "saved_s_per_iteration": saved, "share_saved": saved / fast_iteration if fast_iteration else 0.0,
        }
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="500 frames/updates, 1 generation")
    parser.add_argument("--env", default="halfcheetah")
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--generations", type=int, default=None)
    parser.add_argument("--compare", action="store_true", help="also time implementation=reference, interleaved, same process")
    parser.add_argument("--ablation", action="store_true", help="also time each fast piece switched back to its reference alone, interleaved")
    parser.add_argument("--capacity", type=int, default=None, help="items per buffer (default: conf/config.yaml's; smoke runs only)")
    parser.add_argument("--max-episode-steps", type=int, default=None, help="ES episode length (default: the task's; smoke runs only)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds per part (medians reported)")
    parser.add_argument("--td3-threads", type=int, default=None, help="td3.num_threads of the tuned configuration (default: conf/config.yaml's)")
    parser.add_argument("--plain", action="store_true", help="also time the plain PyTorch TD3 update (1 and 2 threads), interleaved with the loop's updates")
    parser.add_argument("--out", default=None, help="JSON record (default: benchmarks/results/iteration.json, iteration_ablation.json with --ablation)")
    args = parser.parse_args(argv)
    frames, generations = args.frames or (500 if args.quick else 2000), args.generations or (1 if args.quick else 2)
    report = run(args.env, frames, generations, capacity=args.capacity, compare=args.compare, rounds=args.rounds, td3_threads=args.td3_threads,
                 plain=args.plain, ablation=args.ablation, max_episode_steps=args.max_episode_steps)
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
    for piece, a in report.get("ablation", {}).items():
        print(f"without {piece:14s} {a['iteration_s']:8.1f} s/iteration: saves {a['saved_s_per_iteration']:7.1f} s ({a['share_saved']:6.1%} of the fast iteration); reference: {a['reference']}")
    save_report(report, args.out or ("benchmarks/results/iteration_ablation.json" if args.ablation else "benchmarks/results/iteration.json"))
    return report


if __name__ == "__main__":
    main()
