"""The ways a run stops with one line instead of a traceback.

- :class:`ConfigError`: a configuration value is invalid, found before any work starts;
- ``FloatingPointError`` raised by :func:`check_finite` (and by the TD3 and ES updates): NaN or
  inf in a loss, an episode return or the ES mean; nothing is checkpointed after it;
- :class:`CheckpointWriteError`: a checkpoint could not be written (disk full, file-size limit);
  the previous checkpoint is kept whole.
"""
from __future__ import annotations

import math

import torch


class ConfigError(ValueError):
    """A configuration value is invalid; the message is one line naming the field and what is allowed."""


class CheckpointWriteError(RuntimeError):
    """A checkpoint could not be written; the message is one line naming the directory and the cause."""


def check_finite(name: str, value):
    """Return ``value``; raise FloatingPointError if it (a number or a tensor) holds NaN or inf."""
    if isinstance(value, torch.Tensor):
        bad = int((~torch.isfinite(value)).sum())
        if bad:
            raise FloatingPointError(f"{name} has {bad} non-finite entr{'y' if bad == 1 else 'ies'}")
    elif not math.isfinite(float(value)):
        raise FloatingPointError(f"{name} is {value}")
    return value


def error_line(error: BaseException) -> str:
    """An exception in one line: its type and the first line of its message."""
    text = str(error).strip()
    return f"{type(error).__name__}: {text.splitlines()[0]}"[:300] if text else type(error).__name__
