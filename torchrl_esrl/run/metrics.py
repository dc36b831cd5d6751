"""Run outputs: ``metrics.csv`` (one row per iteration), ``summary.json`` and a TorchRL logger.

``metrics.csv`` is written by hand (``csv.DictWriter``, flushed every row) because it is the
project's stable, column-named record that the report reads; every value also goes to the
TorchRL logger chosen in the config (csv by default, tensorboard or wandb when installed).
"""
from __future__ import annotations

import csv
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

# ES-TD3Buffers' columns (recipes/es_td3.py).
METRIC_COLUMNS = (
    *CORE_COLUMNS[:-1],
    "td3_updates",
    "td3_eval_return",
    "es_eval_return",
    "td3_average",
    "es_average",
    "overwritten",
    "best_return",
    "threshold",
    "good_size",
    "bad_size",
    "noisy_size",
    "es_generation_mean_return",
    "es_generation_max_return",
    "critic_loss",
    "actor_loss",
    "buffer_mode",
    "wall_time_s",
)


class MetricsLog:
    """Appends iteration rows to ``<run_dir>/metrics.csv`` and mirrors them to a TorchRL logger."""

    def __init__(self, run_dir: str | Path, backend: str = "csv", experiment_name: str = "es_td3", columns=METRIC_COLUMNS, logger_kwargs: Mapping | None = None):
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.path = self.run_dir / "metrics.csv"
        self.columns = tuple(columns)
        self.rows: list[dict] = []
        self.logger = get_logger(backend, logger_name=str(self.run_dir / "logs"), experiment_name=experiment_name, **dict(logger_kwargs or {})) if backend else None

    def log(self, row: Mapping) -> None:
        row = {key: row.get(key, "") for key in self.columns}
        new = not self.path.exists()
        with self.path.open("a", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=self.columns)
            if new:
                writer.writeheader()
            writer.writerow(row)
        self.rows.append(row)
        if self.logger is not None:
            step = int(row.get("td3_frames") or row.get("iteration") or 0)  # ES alone has no TD3 frames
            for key, value in row.items():
                if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
                    self.logger.log_scalar(key, float(value), step=step)


def read_metrics(path: str | Path) -> list[dict]:
    """Rows of a ``metrics.csv`` with numbers parsed."""
    rows = []
    with Path(path).open() as handle:
        for row in csv.DictReader(handle):
            rows.append({key: _number(value) for key, value in row.items()})
    return rows


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
