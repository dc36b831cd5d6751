"""The logger's position in a checkpoint: rows written after it are written again, once; rows
lost or damaged before it are written back from the checkpoint's copy."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from torchrl_esrl.run.metrics import damage

METRICS = "metrics.csv"
KEPT_SUFFIX = ".csv"  # files whose bytes a checkpoint keeps: metrics.csv and the csv logger's, one row per iteration


class MetricsDamaged(ValueError):
    """``metrics.csv`` lacks or garbles rows a checkpoint counts, and the checkpoint keeps no copy
    of them (a checkpoint written before checkpoints kept one)."""


class LoggerPosition:
    """Byte sizes of ``metrics.csv`` and the TorchRL logger's files, and the bytes of the text ones
    (``*.csv``); restoring truncates each file to its size, so rows written after the checkpoint are
    written again, once, by the resumed run, and writes back from the copy a file that no longer
    begins with the checkpoint's bytes (cut or garbled by a crash or a full disk; :attr:`rewritten`)."""

    def __init__(self, run_dir: Path):
        self.run_dir = Path(run_dir)
        self.rewritten: list[str] = []  # the files the last restore wrote back from its copy

    def _files(self) -> list[Path]:
        files = [self.run_dir / METRICS]
        logs = self.run_dir / "logs"
        if logs.exists():
            files += sorted(p for p in logs.rglob("*") if p.is_file())
        return [p for p in files if p.exists()]

    def state_dict(self) -> dict:
        sizes, kept, copy = {}, {}, bytearray()
        for path in self._files():
            name = str(path.relative_to(self.run_dir))
            if path.suffix == KEPT_SUFFIX:
                data = path.read_bytes()
                kept[name] = [len(copy), len(data)]
                copy += data
                sizes[name] = len(data)
            else:
                sizes[name] = path.stat().st_size
        state = {"files": sizes}
        if copy:  # (a tensor of no bytes cannot be memory-mapped)
            state["kept"], state["bytes"] = kept, np.frombuffer(bytes(copy), dtype=np.uint8).copy()
        return state

    def load_state_dict(self, state: dict) -> None:
        sizes, kept = state["files"], state.get("kept", {})
        copy = np.asarray(state["bytes"]).tobytes() if kept else b""
        if METRICS in sizes and METRICS not in kept:  # checked before any file is touched
            self._check_covers(METRICS, sizes[METRICS])
        self.rewritten = []
        for path in self._files():
            if str(path.relative_to(self.run_dir)) not in sizes:
                path.unlink()  # created after the checkpoint
        for name, size in sizes.items():
            path = self.run_dir / name
            if name in kept:
                offset, length = kept[name]
                saved = copy[offset: offset + length]
                if _head(path, length) != saved:
                    _write(path, saved)
                    self.rewritten.append(name)
                    continue
            if path.exists() and path.stat().st_size > size:
                os.truncate(path, size)

    def _check_covers(self, name: str, size: int) -> None:
        """:class:`MetricsDamaged` where the file ``name`` lacks the ``size`` bytes the checkpoint
        counts or they are not whole rows."""
        path = self.run_dir / name
        held = path.stat().st_size if path.exists() else None
        if held is None or held < size:
            now = "is missing" if held is None else f"holds {held} bytes"
            raise MetricsDamaged(f"{path} {now}, this checkpoint counts {size}: rows written before it are lost, and it keeps no copy of them")
        wrong = damage(_head(path, size))
        if wrong is not None:
            raise MetricsDamaged(f"{path} is damaged ({wrong}) before the {size} bytes this checkpoint counts, and it keeps no copy of them")


def _head(path: Path, length: int) -> bytes | None:
    """The first ``length`` bytes of ``path`` (None where it does not exist)."""
    if not path.exists():
        return None
    with path.open("rb") as handle:
        return handle.read(length)


def _write(path: Path, data: bytes) -> None:
    """``path`` holds ``data``: written beside it, then renamed over it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    staged = path.with_name(path.name + ".restored")
    staged.write_bytes(data)
    staged.replace(path)
