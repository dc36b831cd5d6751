"""A paper run's iteration against the float32 floor of the machine it ran on, from two records of
one sitting: ``benchmarks.full_scale`` (a whole iteration of the run, resumed from its checkpoint:
its time and the work it did) and ``benchmarks.bounds`` minutes apart (the floor's parts).

The floor of an iteration is its essential work at the speed of its slowest unavoidable parts:

- its ES frames at raw ``mujoco.batch`` physics on both cores: ``bounds``' per-step physics of one
  chunk of mirrored pairs on one core (fixed controls, its first steps from reset), or with
  ``--es-population``, that record's ``raw`` rate on both cores (fixed controls, whole episodes:
  on Ant, whose contacts cost more later in an episode, the slower and truer of the two), or with
  ``--physics raw_replay`` its ``raw_replay`` rate (the physics of the episodes its population
  played: other states than fixed controls reach, so a floor of its own; neither is the timed
  iteration's own population);
- its TD3 frames at the same physics per member step, on one core (one env, stepped in turn);
- its TD3 updates at the time of their float32 matrix products alone (``bounds``' products, the
  best of its thread counts).

Everything else (the population's forward, the update's other work, sampling, evaluation episodes,
checkpoints) is above the floor, so the floor is a lower bound and ``iteration / floor`` is at least
the run's distance from it.

Usage: ``python -m benchmarks.run_floor --full-scale <full_scale.json> --bounds <bounds.json>
[--es-population <es_population.json> [--physics raw|raw_replay]] [--out PATH]``
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from benchmarks.common import save_report

CORES = 2  # where a bounds record names no core count
PHYSICS = {"raw": "raw, whole episodes", "raw_replay": "raw_replay, the episodes its population played"}  # es_population's rates


def floor_parts(work: dict, physics_per_step_s: float, members: int, products_s: float, cores: int = CORES) -> dict:
    """Seconds of each part of the floor of an iteration that did ``work`` (``full_scale``'s
    ``td3_frames``, ``es_frames``, ``td3_updates``), with ``physics_per_step_s`` the time of one step
    of a chunk of ``members`` on one core and ``products_s`` one update's products.

    >>> parts = floor_parts({"td3_frames": 100, "es_frames": 6000, "td3_updates": 100}, 0.03, 30, 0.002)
    >>> parts["es_physics_s"], parts["td3_physics_s"], round(parts["td3_products_s"], 6), round(parts["floor_s"], 6)
    (3.0, 0.1, 0.2, 3.3)
    """
    per_member_step = physics_per_step_s / members
    parts = {
        "es_physics_s": work["es_frames"] * per_member_step / cores,
        "td3_physics_s": work["td3_frames"] * per_member_step,
        "td3_products_s": work["td3_updates"] * products_s,
    }
    return {**parts, "floor_s": sum(parts.values())}


def env_of(full_scale: dict) -> str:
    """The gymnasium id of the run ``full_scale`` timed (its saved Hydra config)."""
    from omegaconf import OmegaConf

    return OmegaConf.load(Path(full_scale["run_dir"]) / ".hydra" / "config.yaml").env.id


def against_floor(full_scale: dict, bounds: dict, es_population: dict | None = None, name: str = "now", physics: str = "raw") -> dict:
    """Each timed iteration of ``full_scale``'s ``name`` tree against the floor ``bounds`` (and
    ``es_population``'s ``physics`` rate, ``raw`` or ``raw_replay``, where given) gives for its task."""
    env = env_of(full_scale)
    td3, es = bounds["td3"][env], bounds["es"][env]
    products = {key: method["s_per_call"] for key, method in td3["methods"].items() if key.startswith("products_") and "bf16" not in key}
    products_key = min(products, key=products.get)
    cores = int(bounds.get("machine", {}).get("cpus") or CORES)  # the cores the floor's physics ran on
    per_step, members, source = es["per_step_s"]["physics"], 2 * es["pairs"], "bounds: one chunk's first steps"
    if es_population is not None:  # one member step per core at the rate of all cores
        rate = es_population["envs"][env][physics]["steps_per_s"]
        per_step, members, source = cores / rate, 1, f"es_population: {PHYSICS[physics]}"
    rows = []
    for timed in full_scale["times"][name]:
        parts = floor_parts(timed["work"], per_step, members, products[products_key], cores)
        rows.append({**timed, **parts, "over_floor": timed["iteration_s"] / parts["floor_s"]})
    return {
        "env": env, "from_iteration": full_scale["from_iteration"], "commit": full_scale["commits"][name],
        "physics": source, "physics_per_step_s": per_step, "members_per_step": members,
        "products": products_key, "products_s": products[products_key], "iterations": rows,
        "over_floor": statistics.median(row["over_floor"] for row in rows),
        "full_scale_machine": full_scale.get("machine"), "bounds_machine": bounds.get("machine"),
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--full-scale", type=Path, required=True)
    parser.add_argument("--bounds", type=Path, required=True)
    parser.add_argument("--es-population", type=Path, default=None, help="its physics (--physics) instead of bounds' chunk")
    parser.add_argument("--physics", choices=sorted(PHYSICS), default="raw", help="which of --es-population's rates (default: raw)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    if args.physics != "raw" and args.es_population is None:
        parser.error("--physics: needs --es-population (bounds' chunk has one rate only)")
    full_scale, bounds = (json.loads(path.read_text()) for path in (args.full_scale, args.bounds))
    es_population = json.loads(args.es_population.read_text()) if args.es_population else None
    report = save_report(against_floor(full_scale, bounds, es_population, physics=args.physics), args.out)
    for row in report["iterations"]:
        print(f"{report['env']} iteration {row['iteration'] + 1}: {row['iteration_s']:,.1f} s against a floor of {row['floor_s']:,.1f} s "
              f"(ES physics {row['es_physics_s']:,.1f}, TD3 physics {row['td3_physics_s']:,.1f}, update products {row['td3_products_s']:,.1f}): "
              f"{row['over_floor']:.2f}x ({report['physics']})")
    return report


if __name__ == "__main__":
    main()
