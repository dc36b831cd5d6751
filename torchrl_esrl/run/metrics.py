"""Run outputs: ``metrics.csv`` (one row per iteration), ``summary.json`` and a TorchRL logger.

``metrics.csv`` is written by hand (``csv.DictWriter``, flushed every row) because it is the
project's stable, column-named record that the report reads; every value also goes to the
TorchRL logger chosen in the config (csv by default, tensorboard or wandb when installed).
"""
from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Mapping
from pathlib import Path

from torchrl.record.loggers import get_logger

# Columns every recipe writes (torchrl_esrl.run.harness): the report reads these.
CORE_COLUMNS = (
    "iteration",
    "td3_frames",
    "es_frames",
    "total_frames",
    "eval_return",  # deterministic evaluation of the policy the algorithm returns
    "wall_time_s",
)


class MetricsLog:
    """Appends iteration rows to ``<run_dir>/metrics.csv`` and mirrors them to a TorchRL logger.

    The columns are the keys of the first row (or the header of the file a resumed run
    continues); a later row with other keys raises :class:`KeyError` rather than losing them.
    """

    def __init__(self, run_dir: str | Path, backend: str, experiment_name: str, logger_kwargs: Mapping | None = None):
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.path = self.run_dir / "metrics.csv"
        self.logger = get_logger(backend, logger_name=str(self.run_dir / "logs"), experiment_name=experiment_name, **dict(logger_kwargs or {})) if backend else None

    def columns(self) -> tuple[str, ...] | None:
        """The header of ``metrics.csv`` (None before its first row)."""
        if not self.path.exists() or self.path.stat().st_size == 0:
            return None
        with self.path.open(newline="") as handle:
            return tuple(next(csv.reader(handle)))

    def log(self, row: Mapping) -> None:
        columns = self.columns()
        if columns is not None and tuple(row) != columns:
            unknown, missing = sorted(set(row) - set(columns)), sorted(set(columns) - set(row))
            raise KeyError(f"metrics row does not match the columns of {self.path}: unknown {unknown}, missing {missing} (or in another order)")
        with self.path.open("a", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=tuple(row))
            if columns is None:
                writer.writeheader()
            writer.writerow(row)
        if self.logger is not None:
            step = int(row.get("td3_frames") or row.get("iteration") or 0)  # ES alone has no TD3 frames
            for key, value in row.items():
                if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
                    self.logger.log_scalar(key, float(value), step=step)


def read_metrics(path: str | Path) -> list[dict]:
    """Rows of a ``metrics.csv`` with numbers parsed; a :class:`ValueError` naming the file and the
    line where the file is not whole rows (:func:`damage`: cut by a kill or a full disk, garbled)."""
    path = Path(path)
    data = path.read_bytes()
    wrong = damage(data)
    if wrong is not None:
        raise ValueError(f"{path} is damaged: {wrong}")
    return [{key: _number(value) for key, value in row.items()} for row in csv.DictReader(io.StringIO(data.decode(), newline=""))]


def damage(data: bytes) -> str | None:
    """Where ``data``, the bytes of a ``metrics.csv``, is not a header and whole rows, in words
    (a line cut short, a line with more or fewer fields than the header, a NUL byte, bytes that are
    not text); None where it is whole."""
    if not data:
        return None
    if b"\0" in data:
        return f"line {_line_of(data, data.index(0))} holds a NUL byte"
    if not data.endswith(b"\n"):
        return f"line {_line_of(data, len(data))} is cut short (no line end)"
    try:
        lines = list(csv.reader(io.StringIO(data.decode(), newline="")))
    except (UnicodeDecodeError, csv.Error) as error:
        return f"it does not parse as CSV ({error})"
    for number, fields in enumerate(lines[1:], 2):
        if len(fields) != len(lines[0]):
            return f"line {number} has {len(fields)} field{'' if len(fields) == 1 else 's'}, the header {len(lines[0])}"
    return None


def _line_of(data: bytes, offset: int) -> int:
    """The number (from 1) of the line of ``data`` that holds byte ``offset``."""
    return data.count(b"\n", 0, offset) + 1


def _number(value: str):
    if value in ("True", "False"):
        return value == "True"
    try:
        number = float(value)
    except ValueError:
        return value
    return int(number) if number.is_integer() and "." not in value and "e" not in value.lower() else number


def write_json(path: str | Path, payload: Mapping) -> None:
    """Write JSON atomically (temporary file, then rename) so a kill never leaves half a file."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(payload, indent=2, default=float))
    tmp.replace(path)
