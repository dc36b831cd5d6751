"""One writer per run directory: an advisory ``fcntl.flock`` on ``<run dir>/.lock``.

The lock is taken before anything writes into the directory (``ValidateBeforeRun`` for a single
run, the task function for a multirun job) and held until the process ends (a multirun job
releases it when the job ends). The kernel releases a flock when its holder dies, however it
dies (``kill -9``, a lost node): a stale lock cannot block a rerun. The file also holds a short
record of the holder (pid, host, start time), which the refusal names. Where the filesystem
does not support ``flock`` (docs/runs.md), the run goes on unguarded, saying so in one line.
"""
from __future__ import annotations

import errno
import fcntl
import json
import os
import socket
import sys
from datetime import datetime, timezone
from pathlib import Path

from torchrl_esrl.errors import ConfigError

LOCK_NAME = ".lock"
UNSUPPORTED = (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL)  # flock not available on this filesystem


class RunLock:
    """The exclusive lock of one run directory (:meth:`acquire`, :meth:`release`)."""

    def __init__(self, run_dir: str | Path):
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / LOCK_NAME
        self.fd: int | None = None

    def acquire(self, field: str = "hydra.run.dir") -> RunLock:
        """Take the lock, or raise :class:`ConfigError` naming the live holder. Creates the run
        directory and the lock file if needed; writes the record only once the lock is held."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _describe(_read_record(fd))
            os.close(fd)
            raise ConfigError(
                f"{field}: {self.run_dir} is being written by another run ({holder}); nothing was changed "
                "(allowed: wait for that run to end, or stop it and rerun this command to resume it; fresh=true or another hydra.run.dir for a new run)"
            ) from None
        except OSError as error:
            if error.errno not in UNSUPPORTED:
                os.close(fd)
                raise
            print(f"warning: {self.run_dir} is on a filesystem without file locks ({error.strerror}); this run does not keep other runs out of it", file=sys.stderr, flush=True)
        record = {"pid": os.getpid(), "host": socket.gethostname(), "since": datetime.now(timezone.utc).astimezone().isoformat(timespec="seconds")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(record) + "\n").encode(), 0)
        self.fd = fd
        return self

    def release(self) -> None:
        if self.fd is not None:
            os.close(self.fd)  # closing the last descriptor releases the flock
            self.fd = None


def holder(run_dir: str | Path) -> dict | None:
    """The record of the directory's last (or current) writer, None if there is none."""
    try:
        fd = os.open(Path(run_dir) / LOCK_NAME, os.O_RDONLY)
    except OSError:
        return None
    try:
        return _read_record(fd)
    finally:
        os.close(fd)


def _read_record(fd: int) -> dict | None:
    try:
        return json.loads(os.pread(fd, 4096, 0).decode())
    except (OSError, ValueError):
        return None


def _describe(record: dict | None) -> str:
    if not record:
        return "its record is not written yet"
    return f"pid {record.get('pid')} on {record.get('host')}, since {record.get('since')}"
