"""The checkpoint of a run: everything the rest of the run depends on, so that a run killed at
any moment and resumed from its last checkpoint writes the same ``metrics.csv`` as a run never
interrupted (``wall_time_s`` excepted). What ES-TD3Buffers saves (the baselines save the
subset they have):

- TD3: actor, twin critics, target networks, both Adam optimisers, update count
  (:meth:`TD3.state_dict`), and the exploration module;
- ES: mean, Adam state, noise generator, generation (:meth:`OpenES.state_dict`); the ES
  collector's stream of episode seeds and frame count;
- the threshold (best return), the overwrite rule's window and decision history;
- the three buffers with their contents (:meth:`MultiBuffer.state_dict`, TorchRL storages);
- the TD3 environment mid-episode (:class:`TD3EnvState`): MuJoCo's integration state
  (``mj_getState``: qpos, qvel, act, time, warm start...), gymnasium's ``np_random`` and its
  wrappers' counters (``TimeLimit`` elapsed steps...), and the TorchRL ``Collector``'s carried
  tensordict (``episode_reward`` of ``RewardSum``, ``step_count`` of ``StepCounter``,
  trajectory ids) and counters;
- the global RNGs (torch, numpy, Python: exploration noise, buffer sampling and TD3's target
  smoothing draw from torch's), TorchRL's :class:`~torchrl.checkpoint.GlobalRNGState`;
- the loop position (:class:`~torchrl_esrl.run.progress.RunProgress`: iteration, TD3 frames,
  the TD3 phase in progress) and the logger's position
  (:class:`~torchrl_esrl.run.logger_position.LoggerPosition`), with a copy of ``metrics.csv``
  and the csv logger's files, so that rows cut or garbled before the checkpoint (a crash, a full
  disk) are written back on restore, in one line on stderr.

Files are written by TorchRL's :class:`~torchrl.checkpoint.Checkpoint` (staged in a hidden
directory, then renamed) under :class:`~torchrl.checkpoint.CheckpointRotation`
(``<run_dir>/checkpoints/checkpoint-<td3 frames + iteration + phase steps>``, :attr:`RunProgress.checkpoint_step`; ``checkpoint.keep_last`` kept), so a
kill during a save leaves the previous checkpoint whole. Checkpoints are taken at every
iteration boundary and every ``checkpoint.every_frames`` TD3 frames (mid-phase, possibly
mid-episode); :meth:`RunCheckpoint.save` refuses to write non-finite parameters, so nothing
is saved after a numerical fault. A save that fails (disk full) raises
:class:`~torchrl_esrl.errors.CheckpointWriteError`; TorchRL removes its staging folder and the
previous checkpoint stays whole.

Before a save, the free space of the checkpoint folder is checked against one checkpoint's size
(``expected_bytes``, the estimate of :mod:`~torchrl_esrl.run.capacity`): a full disk stops the run
with :class:`~torchrl_esrl.errors.CheckpointWriteError` before any byte is written. (Tensors are
written through memory maps, and a memory-mapped write that finds no room ends the process with
SIGBUS instead of an error.)

Every checkpoint proves it is whole: its last component, ``~digests`` (:class:`DigestAdapter`),
records the SHA-256 of every file of the other components and of the manifest's metadata,
inside TorchRL's staging folder, so the digests are published with the files they cover. A
checkpoint that cannot be read (:func:`unreadable`: its manifest, a file it lists, a JSON file
that does not parse, a tensor file of the wrong size, a file or the metadata that does not
match its digest) is skipped on restore with one line on stderr, and the previous one is
restored instead. A checkpoint without ``~digests`` (written before they were recorded) is
checked as before, without digests. The manifest's metadata names the algorithm,
so that a run directory of another recipe is told apart before anything is built.
"""
from __future__ import annotations

import errno
import hashlib
import json
import logging
import math
import os
import re
import shutil
import sys
from pathlib import Path

import torch
from torchrl.checkpoint import Checkpoint, CheckpointAdapter, CheckpointError, CheckpointRotation, GlobalRNGState, StateDictCheckpointAdapter

from torchrl_esrl.errors import CheckpointWriteError, ConfigError

from torchrl_esrl.data.multibuffer import MultiBuffer
from torchrl_esrl.run.logger_position import LoggerPosition, MetricsDamaged
from torchrl_esrl.run.progress import RunProgress
from torchrl_esrl.threads import RunThreads

CHECKPOINT_DIR = "checkpoints"
log = logging.getLogger(__name__)  # under torchrl_esrl.run: the run directory's <recipe>.log only
CHECKPOINT_NAME = re.compile(r"checkpoint-(\d+)(\.torchrl)?")  # CheckpointRotation's entries
DIGESTS = "~digests"  # after every other name: TorchRL saves components in name order, so this one last
DIGEST_FILE = "digests.json"
HASH = "sha256"  # about twice blake2b's speed here (SHA-NI); docs/runs.md


def file_digest(path: Path) -> str:
    """The SHA-256 of a file's bytes, remembered for the file as it is now (device, inode, size,
    modification time), so a checkpoint checked twice in one process is read once."""
    stat = path.stat()
    key = (stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns)
    if key not in _digests:
        with path.open("rb") as handle:
            _digests[key] = hashlib.file_digest(handle, HASH).hexdigest()
    return _digests[key]


_digests: dict[tuple, str] = {}


def metadata_digest(metadata) -> str:
    """The SHA-256 of the manifest metadata, as JSON with sorted keys."""
    return hashlib.new(HASH, json.dumps(metadata, sort_keys=True).encode()).hexdigest()


class Digests:
    """The ``~digests`` component: holds the metadata of the checkpoint being saved."""

    def __init__(self):
        self.metadata: dict = {}


class DigestAdapter(CheckpointAdapter):
    """Saves the digests of every file the checkpoint's other components wrote (the component
    saved last, in TorchRL's staging folder) and of its metadata; loads nothing."""

    adapter_id = "torchrl_esrl.digests"
    format_version = 1

    def save(self, component: Digests, path: Path, *, args, kwargs):
        path.mkdir(parents=True, exist_ok=True)
        root = path.parent.parent  # the checkpoint being written: <stage>/components/<this component>
        files = {
            file.relative_to(root).as_posix(): file_digest(file)
            for file in sorted((root / "components").rglob("*"))
            if file.is_file() and path not in file.parents
        }
        record = {"hash": HASH, "files": files, "metadata": metadata_digest(component.metadata)}
        (path / DIGEST_FILE).write_text(json.dumps(record, indent=1, sort_keys=True) + "\n", encoding="utf-8")

    def load(self, component, path, *, map_location, tensor_load_kwargs, args, kwargs):
        return None  # checked by unreadable() before any load


class RunCheckpoint:
    """Saves and restores a whole run of Algorithm 1 in ``<run_dir>/checkpoints``.

    Args:
        run_dir: the run directory (metrics.csv, logs/ and checkpoints/ live there).
        config: the resolved config as a plain dict (saved; compared on resume, see resume.py).
        every_frames: also save every this many TD3 frames (0: iteration boundaries only).
        algorithm: the algorithm's name (``summary.json``'s), saved in the metadata.
        components: name -> object with ``state_dict``/``load_state_dict``.
    """

    def __init__(self, run_dir: str | Path, config: dict, every_frames: int, keep_last: int, algorithm: str | None = None, expected_bytes: int = 0,
                 every_generations: int = 0, **components):
        self.run_dir = Path(run_dir)
        self.expected_bytes = int(expected_bytes)  # one checkpoint's size at most; 0: no check of the free space
        self.every_frames = int(every_frames)
        self.every_generations = int(every_generations)
        self.rotation = CheckpointRotation(self.run_dir / CHECKPOINT_DIR, keep_last=keep_last)
        self.progress: RunProgress = components["progress"]
        self.config = config
        self.algorithm = algorithm
        self.components = components
        self.digests = Digests()
        self.logger_position = LoggerPosition(self.run_dir)
        parts = {
            "rng": GlobalRNGState(),
            "logger": self.logger_position,
            "threads": RunThreads(),  # the count between phases, not the one of the phase a stop interrupts
            **components,
        }
        self.loaded = sorted(parts)  # what a restore loads: all but the digests
        self.checkpoint = (
            Checkpoint(**parts, **{DIGESTS: self.digests})
            .register_adapter(MultiBuffer, StateDictCheckpointAdapter())  # a ReplayBuffer, saved by state_dict as ever (not dump)
            .register_adapter(Digests, DigestAdapter())
        )
        self._last_frames = self.progress.frames_now

    def latest(self) -> Path | None:
        return self.rotation.latest() if (self.run_dir / CHECKPOINT_DIR).exists() else None

    def save(self) -> Path:
        """Write a checkpoint of the current state (refuses non-finite parameters; a failed write
        raises :class:`CheckpointWriteError` and leaves the previous checkpoint whole)."""
        for name, component in self.components.items():
            for tensor in _parameters_of(component):
                if not torch.isfinite(tensor).all():
                    raise FloatingPointError(f"refusing to checkpoint non-finite parameters of '{name}'")
        self._last_frames = self.progress.frames_now
        step = self.progress.checkpoint_step  # grows with every save
        self._saved_step = step
        metadata = {"iteration": self.progress.iteration, "td3_frames": self.progress.frames_now, "config": self.config, "algorithm": self.algorithm}
        self.digests.metadata = json.loads(json.dumps(metadata))  # as the manifest will read back
        try:
            self._check_room()
            return self.rotation.save(self.checkpoint, step=step, metadata=metadata)
        except (OSError, RuntimeError) as error:
            cause = _write_failure(error)
            if cause is None:
                raise
            kept = newest_readable(self.run_dir)[0]
            raise CheckpointWriteError(
                f"could not write a checkpoint in {self.run_dir / CHECKPOINT_DIR} ({cause}); run stopped, "
                f"{f'last good checkpoint kept: {kept.name}' if kept else 'no earlier checkpoint'}; rerun the same command to resume once there is room"
            ) from None

    def _check_room(self) -> None:
        """ENOSPC before writing, where one checkpoint would not fit (a memory-mapped write
        into a full filesystem would end the process with SIGBUS)."""
        if not self.expected_bytes:
            return
        directory = self.run_dir / CHECKPOINT_DIR
        directory.mkdir(parents=True, exist_ok=True)
        free = shutil.disk_usage(directory).free
        if free < self.expected_bytes:
            from torchrl_esrl.run.capacity import human

            raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)}: a checkpoint needs about {human(self.expected_bytes)}, {human(free)} is free")

    def save_if_new(self) -> Path:
        """:meth:`save`, unless the last save was at this very point (a stop right after one)."""
        if getattr(self, "_saved_step", None) == self.progress.checkpoint_step and self.latest() is not None:
            return self.latest()
        return self.save()

    def maybe_save_mid_phase(self, *_):
        """``td3_phase`` ``on_batch`` hook: save once every ``every_frames`` TD3 frames."""
        if self.every_frames and self.progress.frames_now // self.every_frames > self._last_frames // self.every_frames:
            self.save()

    def maybe_save_after_generation(self, done: int, total: int) -> None:
        """After the ES phase's ``done``-th generation of ``total`` in the iteration (run inline):
        save once every ``every_generations`` of them, the last excepted (the iteration's end saves)."""
        if self.every_generations and done % self.every_generations == 0 and done < total:
            self.save_if_new()

    def restore(self, path: str | Path | None = None) -> Path | None:
        """Load ``path`` into the live components; by default the newest checkpoint that can be
        read, saying in one line on stderr for each newer one why it was skipped. None if the run
        directory has no checkpoint; :class:`ConfigError` if it has some and none can be read."""
        self._remove_dead_stages()
        if path is not None:
            self.checkpoint.load(path, components=self.loaded)
            self._last_frames = self.progress.frames_now
            return Path(path)
        skipped = []
        for candidate in checkpoint_paths(self.run_dir):
            reason = unreadable(candidate)
            if reason is None:
                try:
                    self.checkpoint.load(candidate, components=self.loaded)  # every component again from the next one if this fails
                except CheckpointError as error:  # (MetricsDamaged: the run's rows, not the checkpoint, are damaged)
                    reason = f"logger: {_first_line(error.__cause__)}" if isinstance(error.__cause__, MetricsDamaged) else _first_line(error)
            if reason is not None:
                skipped.append((candidate, reason))
                continue
            for damaged, why in skipped:
                _say(f"checkpoint {damaged} cannot be read ({why}); resuming from {candidate.name}")
            if self.logger_position.rewritten:
                _say(f"{', '.join(self.logger_position.rewritten)} in {self.run_dir} did not begin with the rows {candidate.name} counts (cut or damaged since); written back from its copy")
            self._last_frames = self.progress.frames_now
            return candidate
        if skipped:
            raise ConfigError(no_readable_checkpoint(self.run_dir, skipped))
        return None

    def _remove_dead_stages(self) -> None:
        """A save killed midway leaves its hidden staging folder (TorchRL removes one only on an
        exception). One run writes here at a time, so any found before it starts are dead."""
        for stage in (self.run_dir / CHECKPOINT_DIR).glob(".*.stage-*"):
            shutil.rmtree(stage, ignore_errors=True)


def _say(line: str) -> None:
    """A line of the restore: in the run's log and on stderr."""
    log.warning(line)
    print(line, file=sys.stderr, flush=True)


def checkpoint_paths(run_dir: str | Path) -> list[Path]:
    """Every entry of ``<run_dir>/checkpoints`` named as a checkpoint, readable or not, newest first."""
    directory = Path(run_dir) / CHECKPOINT_DIR
    if not directory.is_dir():
        return []
    named = [(int(match.group(1)), path) for path in directory.iterdir() if (match := CHECKPOINT_NAME.fullmatch(path.name))]
    return [path for _, path in sorted(named, reverse=True)]


def unreadable(path: str | Path) -> str | None:
    """Why the checkpoint at ``path`` cannot be restored, or None: its manifest (TorchRL's
    check), every file it lists, every JSON file, every tensor file's size against the shape
    and dtype its TensorDict metadata gives, then every file and the metadata against their
    digests (where the checkpoint has them)."""
    path = Path(path)
    try:
        manifest = Checkpoint.manifest(path)
    except (CheckpointError, OSError, ValueError) as error:
        return f"manifest: {_first_line(error)}"
    if not path.is_dir():
        return None  # an archive: TorchRL checks its members on load
    for name, record in manifest["components"].items():
        root = path / record["path"]
        for relative in record.get("files", []):
            file = root / relative
            if not file.is_file():
                return f"{name}: {relative} is missing"
            if file.suffix == ".json":
                try:
                    meta = json.loads(file.read_text(encoding="utf-8"))
                except (OSError, ValueError) as error:
                    return f"{name}: {relative} does not parse ({_first_line(error)})"
                if file.name == "meta.json" and (wrong := _wrong_tensor_size(file.parent, meta)):
                    return f"{name}: {wrong}"
    return _wrong_digest(path, manifest)


def _wrong_digest(path: Path, manifest: dict) -> str | None:
    """A file of the checkpoint, or its metadata, that does not match the digest recorded when
    it was written; None for a checkpoint without digests."""
    components = manifest["components"]
    if DIGESTS not in components:
        return None
    try:
        record = json.loads((path / components[DIGESTS]["path"] / DIGEST_FILE).read_text(encoding="utf-8"))
        recorded, hash_name, metadata = dict(record["files"]), record["hash"], record["metadata"]
    except (OSError, ValueError, KeyError, TypeError) as error:
        return f"{DIGESTS}: {DIGEST_FILE} does not parse ({_first_line(error)})"
    if hash_name != HASH:
        return f"{DIGESTS}: digests by {hash_name!r}, this version checks {HASH!r}"
    if metadata != metadata_digest(manifest.get("metadata")):
        return f"manifest: its metadata does not match its {HASH} digest"
    listed = {f"{record_['path']}/{relative}": name for name, record_ in components.items() if name != DIGESTS for relative in record_.get("files", [])}
    if set(listed) != set(recorded):
        return f"{DIGESTS}: the manifest lists other files than the digests cover"
    for relative, digest in recorded.items():
        if file_digest(path / relative) != digest:
            return f"{listed[relative]}: {relative.split('/', 2)[-1]} does not match its {HASH} digest"
    return None


def _wrong_tensor_size(folder: Path, meta: dict) -> str | None:
    """A tensor file of a TensorDict saved with ``tensordict.save`` whose size does not match its metadata."""
    for key, entry in meta.items():
        if not (isinstance(entry, dict) and "shape" in entry and "dtype" in entry) or entry.get("is_nested"):
            continue
        dtype = getattr(torch, str(entry["dtype"]).removeprefix("torch."), None)
        if not isinstance(dtype, torch.dtype):
            continue
        file = folder / f"{key}.memmap"
        expected = math.prod(entry["shape"]) * dtype.itemsize
        size = file.stat().st_size if file.is_file() else None
        if size is not None and size != expected:
            return f"{folder.name}/{file.name} holds {size} bytes, its metadata says {expected}"
    return None


def newest_readable(run_dir: str | Path) -> tuple[Path | None, list[tuple[Path, str]]]:
    """The newest checkpoint of ``run_dir`` that :func:`unreadable` passes, and the newer ones it does not (with why)."""
    skipped = []
    for path in checkpoint_paths(run_dir):
        reason = unreadable(path)
        if reason is None:
            return path, skipped
        skipped.append((path, reason))
    return None, skipped


def no_readable_checkpoint(run_dir: str | Path, skipped: list[tuple[Path, str]]) -> str:
    """The one line of a run directory whose checkpoints all fail to read."""
    newest, why = skipped[0]
    return (
        f"no checkpoint in {Path(run_dir) / CHECKPOINT_DIR} can be read ({len(skipped)} tried; newest {newest.name}: {why}); "
        "nothing was changed (allowed: restore the checkpoints, or fresh=true or another hydra.run.dir for a new run)"
    )


def saved_metadata(run_dir: str | Path) -> dict | None:
    """The metadata (config, algorithm, position) of the newest readable checkpoint of ``run_dir``."""
    path = newest_readable(run_dir)[0]
    return None if path is None else Checkpoint.manifest(path)["metadata"]


def saved_config(run_dir: str | Path) -> dict | None:
    """The config stored with the newest readable checkpoint of ``run_dir`` (None if it has none)."""
    metadata = saved_metadata(run_dir)
    return None if metadata is None else metadata["config"]


def _write_failure(error: BaseException) -> str | None:
    """The cause of a failed write (an ``OSError``, or torch's ``RuntimeError`` for a memory-mapped
    file it could not size, which ends in the errno: ``... File too large (27)``); None otherwise."""
    if isinstance(error, OSError):
        return error.strerror or str(error)
    match = re.search(r"\((\d+)\)\s*$", str(error))
    if match and "file" in str(error):
        return os.strerror(int(match.group(1)))
    return None


def _first_line(error: BaseException) -> str:
    text = str(error).strip()
    return (text.splitlines()[0] if text else type(error).__name__)[:300]


def _parameters_of(component):
    if hasattr(component, "mean") and isinstance(getattr(component, "mean"), torch.Tensor):
        yield component.mean.detach()
    loss = getattr(component, "loss", None)
    if isinstance(loss, torch.nn.Module):
        yield from (p.detach() for p in loss.parameters())
