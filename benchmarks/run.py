"""All performance benchmarks in one command: a table and one JSON file.

    python -m benchmarks.run [--quick] [--only td3 buffer iteration memory es] [--out benchmarks/results/all.json]

Each figure is a ratio against a baseline measured in the same run (interleaved repetitions,
medians), except the extrapolated run time and the memory, which are absolute. Each module also
runs alone (``python -m benchmarks.<name>``) and writes its own JSON next to this one.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


from benchmarks import common  # noqa: F401  (sets OMP_WAIT_POLICY before torch loads)
from benchmarks import buffer_sampling, es_population, iteration, memory, td3_update

GIB = 2**30


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="small sizes: a smoke run of every benchmark")
    parser.add_argument("--only", nargs="+", default=["es", "td3", "buffer", "iteration", "memory"])
    parser.add_argument("--out", default="benchmarks/results/all.json")
    args = parser.parse_args(argv)
    quick = ["--quick"] if args.quick else []
    out_dir = Path(args.out).parent
    report, rows = {"command": " ".join(["python -m benchmarks.run", *(argv if argv is not None else sys.argv[1:])]),
                    "machine": common.machine()}, []
    start = time.perf_counter()
    if "es" in args.only:
        es = es_population.main([*quick, "--envs", "HalfCheetah-v5", "--repeats", "1" if args.quick else "2",
                                 "--out", str(out_dir / "es_population.json")])
        report["es_population"] = es
        r = es["envs"]["HalfCheetah-v5"]
        rows.append(("1 ES population, HalfCheetah", "mujoco_batch vs raw physics", r["batched"]["vs_raw"], ">= 0.6x", r["batched"]["vs_raw"] >= 0.6))
        rows.append(("1 ES population, HalfCheetah", "mujoco_batch vs serial gymnasium", r["batched"]["vs_serial"], "(reference)", None))
    if "td3" in args.only:
        td3 = td3_update.main([*quick, "--out", str(out_dir / "td3_update.json")])
        report["td3_update"] = td3
        m = td3["methods"]
        rows.append(("2 TD3 update rate", "TorchRL TD3 (default) vs best plain PyTorch", td3["ratio_vs_best_plain"], ">= 1.2x", td3["met"]))
        rows.append(("2 TD3 update rate", "TorchRL TD3 (default) vs plain, 1 thread", m["torchrl_fast"]["ratio"], "(reference)", None))
        rows.append(("2 TD3 update rate", "stock TD3Loss+SoftUpdate vs plain", m["torchrl_stock"]["ratio"], "(reference)", None))
        rows.append(("2 TD3 update rate", "plain + fused Adam vs plain", m["plain_fused"]["ratio"], "(reference)", None))
    if "buffer" in args.only:
        buf = buffer_sampling.main([*quick, "--out", str(out_dir / "buffer_sampling.json")])
        report["buffer_sampling"] = buf
        m = buf["methods"]
        rows.append(("3 buffer sampling (time)", "MultiBuffer 0.5:0.2:0.3 vs one buffer", m["multibuffer"]["ratio"], "<= 1.2x", buf["met"]))
        rows.append(("3 buffer sampling (time)", "3 x sample() + cat vs one buffer", m["naive"]["ratio"], "(reference)", None))
    if "iteration" in args.only:
        it = iteration.main([*quick, "--out", str(out_dir / "iteration.json")])
        report["iteration"] = it
        rows.append(("4 paper run, HalfCheetah", "20 iterations, extrapolated (h)", it["run_h"], "<= 4 h", it["met"]))
    if "memory" in args.only:
        mem = memory.main([*quick, "--out", str(out_dir / "memory.json")])
        report["memory"] = mem
        rows.append(("5 memory, Ant, 3 x 1M", "projected peak RSS (GiB)", mem["paper_projected_peak_gib"], "< 24 GiB", mem["met"]))
        rows.append(("5 memory, Ant", "measured / computed storage", mem["measured_over_computed"], "(check)", None))
    report["rows"] = [dict(zip(("figure", "what", "value", "goal", "met"), row)) for row in rows]
    report["seconds"] = time.perf_counter() - start
    report["load_average_after"] = common.machine()["load_average"]
    print()
    print(f"| {'figure':30s} | {'what':40s} | {'value':>7s} | {'goal':>11s} | met |")
    print(f"|{'-' * 32}|{'-' * 42}|{'-' * 9}|{'-' * 13}|-----|")
    for figure, what, value, goal, met in rows:
        print(f"| {figure:30s} | {what:40s} | {value:7.2f} | {goal:>11s} | {'' if met is None else ('yes' if met else 'no'):3s} |")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2, default=str))
    print(f"wrote {out}")
    return report


if __name__ == "__main__":
    main()
