"""The logger's position in a checkpoint: rows written after it are written again, once."""
from __future__ import annotations

import os
from pathlib import Path


class LoggerPosition:
    """Byte sizes of ``metrics.csv`` and the TorchRL logger's files; restoring truncates to them,
    so rows written after the checkpoint are written again, once, by the resumed run."""

    def __init__(self, run_dir: Path):
        self.run_dir = Path(run_dir)

    def _files(self) -> list[Path]:
        files = [self.run_dir / "metrics.csv"]
        logs = self.run_dir / "logs"
        if logs.exists():
            files += sorted(p for p in logs.rglob("*") if p.is_file())
        return [p for p in files if p.exists()]

    def state_dict(self) -> dict:
        return {"files": {str(p.relative_to(self.run_dir)): p.stat().st_size for p in self._files()}}

    def load_state_dict(self, state: dict) -> None:
        sizes = state["files"]
        for path in self._files():
            size = sizes.get(str(path.relative_to(self.run_dir)))
            if size is None:
                path.unlink()  # created after the checkpoint
            elif path.stat().st_size > size:
                os.truncate(path, size)
