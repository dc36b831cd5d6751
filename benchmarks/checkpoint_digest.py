"""The cost of checking a paper-size checkpoint's digests (torchrl_esrl/run/checkpoint.py).

Writes one checkpoint as a paper run has it at its largest: three full 1M-transition buffers
(``MultiBuffer``, HalfCheetah-v5's shapes unless ``--env`` names another) and the paper's actor
and twin critics, through ``RunCheckpoint``; then
times, in interleaved rounds, the checks a resume makes (files in the page cache, as right after
a run wrote them):

  structure  ``unreadable()`` without its digest step (manifest, listed files, JSON, tensor sizes)
  digests    the digest step alone (SHA-256 of every file against the recorded digests)
  blake2b    the same bytes through blake2b, the alternative hash
  load       ``RunCheckpoint.restore`` of the checkpoint (TorchRL's load of every component)
  save       one ``RunCheckpoint.save`` (digests included)

Usage: ``python -m benchmarks.checkpoint_digest [--env ENV_ID] [--capacity N] [--repeats R] [--dir DIR] [--out PATH]``.
"""
from __future__ import annotations

import argparse
import hashlib
import tempfile
import time
from pathlib import Path

from benchmarks.common import SHAPES, fill, machine, save_report

import torch
from torchrl.checkpoint import Checkpoint
from torchrl.data import Bounded

from torchrl_esrl.data.multibuffer import MultiBuffer
from torchrl_esrl.modules.networks import make_actor, make_critic
from torchrl_esrl.run import checkpoint as run_checkpoint
from torchrl_esrl.run.checkpoint import RunCheckpoint, unreadable
from torchrl_esrl.run.progress import RunProgress


DEFAULT_ENV = "HalfCheetah-v5"


def build(run_dir: Path, capacity: int, env_id: str = DEFAULT_ENV) -> RunCheckpoint:
    obs_dim, act_dim = SHAPES[env_id]
    buffer = MultiBuffer(ratio=(0.5, 0.2, 0.3), capacity=capacity, batch_size=256)
    for name in buffer.names:
        fill(buffer, capacity, obs_dim, act_dim, name=name)
    actor = make_actor(obs_dim, Bounded(-1.0, 1.0, shape=(act_dim,)))
    critics = torch.nn.ModuleList([make_critic(obs_dim, act_dim) for _ in range(2)])
    return RunCheckpoint(run_dir, {"env": {"id": env_id}}, every_frames=0, keep_last=2, progress=RunProgress(), buffer=buffer, actor=actor, critics=critics)


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def run(capacity: int = 1_000_000, repeats: int = 5, directory: str | None = None, env_id: str = DEFAULT_ENV) -> dict:
    with tempfile.TemporaryDirectory(dir=directory) as tmp:
        checkpoint = build(Path(tmp), capacity, env_id)
        saves = [timed(checkpoint.save) for _ in range(2)]
        path = checkpoint.latest()
        files = [p for p in path.rglob("*") if p.is_file()]
        size = sum(p.stat().st_size for p in files)
        manifest = Checkpoint.manifest(path)
        check_digests = run_checkpoint._wrong_digest
        rounds = {"structure": [], "digests": [], "blake2b": [], "load": []}

        def structure():
            run_checkpoint._wrong_digest = lambda *_: None
            try:
                assert unreadable(path) is None
            finally:
                run_checkpoint._wrong_digest = check_digests

        def digests():
            run_checkpoint._digests.clear()  # no remembered digest: every byte read and hashed
            assert check_digests(path, manifest) is None

        def blake2b():
            for file in files:
                with file.open("rb") as handle:
                    hashlib.file_digest(handle, "blake2b")

        def load():
            assert checkpoint.restore(path) == path

        for _ in range(repeats):
            for name, fn in (("structure", structure), ("digests", digests), ("blake2b", blake2b), ("load", load)):
                rounds[name].append(timed(fn))
        result = {name: {"median_s": sorted(r)[len(r) // 2], "rounds_s": r} for name, r in rounds.items()}
        result["save"] = {"rounds_s": saves}
        return {"env": env_id, "checkpoint_bytes": size, "files": len(files), "capacity": capacity, "results": result, "machine": machine()}


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default=DEFAULT_ENV, choices=sorted(SHAPES), help="whose observation and action sizes the buffers hold")
    parser.add_argument("--capacity", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--dir", default=None, help="where the checkpoint is written (default: the system's temporary folder)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    report = run(args.capacity, args.repeats, args.dir, args.env)
    save_report(report, args.out)
    mb = report["checkpoint_bytes"] / 1e6
    for name, entry in report["results"].items():
        print(f"{name:>9}: {', '.join(f'{s:.2f}' for s in entry['rounds_s'])} s  ({mb:.0f} MB, {report['files']} files)")
