"""The TD3 update of a past commit against the working tree's, timed in one process: the code before a
change against the code after it, in one sitting.

``git archive <base> torchrl_esrl`` is unpacked into a temporary folder as the package
``torchrl_esrl_base`` (its own imports renamed to it), so that both versions' ``TD3`` with
``make_td3``'s fast pieces (the hand-written loss, the foreach soft update, fused Adam) train the
paper's networks (actor 2x256 tanh, twin critics 2x256 ReLU, batch 256) side by side, from the same
initial weights, on batches drawn from one MultiBuffer filled to K at the paper's ratio
(0.5:0.2:0.3), sampling included as in the TD3 phase. Each round times ``calls`` updates of each
version, the order alternating between rounds; the ratio of each round (working tree / base) is
reported with its median and quartiles. Drift of the machine within a round moves both versions.

Usage: ``python -m benchmarks.against_commit --base 23208de [--env Walker2d-v5] [--rounds 40]
[--calls 50] [--threads N] [--capacity N] [--out PATH]``. The base package stays imported (its
modules register what they register, Hydra schemas included): run it as its own process.
"""
from __future__ import annotations

import argparse
import importlib
import io
import re
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

from benchmarks.common import SHAPES, fill, save_report  # sets OMP_WAIT_POLICY, first

import torch
from torchrl.data import Bounded

ROOT = Path(__file__).resolve().parents[1]
BASE_PACKAGE = "torchrl_esrl_base"


def import_base(commit: str, folder: Path) -> str:
    """Unpack ``commit``'s ``torchrl_esrl`` into ``folder`` as :data:`BASE_PACKAGE`, put it on the path;
    returns the full commit id."""
    full = subprocess.run(["git", "rev-parse", commit], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
    archive = subprocess.run(["git", "archive", full, "torchrl_esrl"], cwd=ROOT, capture_output=True, check=True).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        for member in tar.getmembers():
            if not member.isfile():
                continue
            target = folder / BASE_PACKAGE / Path(member.name).relative_to("torchrl_esrl")
            target.parent.mkdir(parents=True, exist_ok=True)
            text = tar.extractfile(member).read()
            if member.name.endswith(".py"):
                text = re.sub(rb"\btorchrl_esrl\b", BASE_PACKAGE.encode(), text)
            target.write_bytes(text)
    sys.path.insert(0, str(folder))
    return full


def fast_td3(package: str, obs_dim: int, act_dim: int):
    """``package``'s TD3 with make_td3's fast pieces on the paper's networks, from seed 0."""
    networks = importlib.import_module(f"{package}.modules.networks")
    td3 = importlib.import_module(f"{package}.objectives.td3")
    spec = Bounded(-torch.ones(act_dim), torch.ones(act_dim), shape=(act_dim,))
    torch.manual_seed(0)
    return td3.TD3(
        networks.make_actor(obs_dim, spec), networks.make_critic(obs_dim, act_dim), spec,
        loss_class=td3.ManualGradTD3Loss, target_update_class=td3.ForeachSoftUpdate, optimizer_impl="fused",
    )


def run(base: str, env_id: str = "Walker2d-v5", rounds: int = 40, calls: int = 50, threads: int | None = None, capacity: int = 25_000) -> dict:
    from torchrl_esrl.data.multibuffer import MultiBuffer

    obs_dim, act_dim = SHAPES[env_id]
    if threads:
        torch.set_num_threads(threads)
    buffer = MultiBuffer(ratio=(0.5, 0.2, 0.3), capacity=capacity, batch_size=256, direct_reads=True)  # as make_multibuffer's fast pieces
    for name in buffer.names:
        fill(buffer, capacity, obs_dim, act_dim, name=name)
    with tempfile.TemporaryDirectory() as folder:
        commit = import_base(base, Path(folder))
        versions = {"base": fast_td3(BASE_PACKAGE, obs_dim, act_dim), "now": fast_td3("torchrl_esrl", obs_dim, act_dim)}
        for td3 in versions.values():
            for _ in range(20):
                td3.update(buffer.sample())
        ms: dict[str, list[float]] = {name: [] for name in versions}
        for index in range(rounds):
            for name in versions if index % 2 == 0 else reversed(versions):
                td3 = versions[name]
                start = time.perf_counter()
                for _ in range(calls):
                    td3.update(buffer.sample())
                ms[name].append((time.perf_counter() - start) / calls * 1e3)
    ratios = sorted(now / before for now, before in zip(ms["now"], ms["base"]))
    quartiles = statistics.quantiles(ratios, n=4)
    return {
        "base": commit,
        "now": subprocess.run(["git", "describe", "--always", "--dirty"], cwd=ROOT, capture_output=True, text=True).stdout.strip(),
        "env": env_id, "batch_size": 256, "rounds": rounds, "calls_per_round": calls, "torch_threads": torch.get_num_threads(),
        "ms_per_update": {name: statistics.median(values) for name, values in ms.items()},
        "ratio_now_over_base": {"median": statistics.median(ratios), "q1": quartiles[0], "q3": quartiles[2]},
        "rounds_ms": ms,
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", required=True, help="the commit to time against (the code before a change)")
    parser.add_argument("--env", default="Walker2d-v5", choices=sorted(SHAPES))
    parser.add_argument("--rounds", type=int, default=40)
    parser.add_argument("--calls", type=int, default=50)
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: the process's)")
    parser.add_argument("--capacity", type=int, default=25_000, help="items per buffer (K at the paper's settings)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    report = save_report(run(args.base, args.env, args.rounds, args.calls, args.threads, args.capacity), args.out)
    ratio = report["ratio_now_over_base"]
    print(f"TD3 update, {report['env']}: base {report['ms_per_update']['base']:.2f} ms, now {report['ms_per_update']['now']:.2f} ms; "
          f"now/base {ratio['median']:.3f} [{ratio['q1']:.3f}, {ratio['q3']:.3f}] over {report['rounds']} rounds")
    return report


if __name__ == "__main__":
    main()
