"""The MultiBuffer of ES-TD3Buffers (paper, Section 3.1 "Multi-Buffers", and Algorithm 1).

Three named TorchRL :class:`~torchrl.data.TensorDictReplayBuffer` s, ``good``, ``bad`` and
``noisy``, composed into one TorchRL :class:`~torchrl.data.ReplayBufferEnsemble` (so a
MultiBuffer *is* a :class:`~torchrl.data.ReplayBuffer`: a TorchRL ``Collector`` or ``Trainer``
can write to it and a TorchRL loss learn from its batches). Every batch holds *exactly* each
buffer's share of a fixed ratio (a:b:c), by largest-remainder rounding, and every item is tagged
with the index of the buffer it came from under ``source_key``: the sampler and storage ensemble
that do it are in :mod:`torchrl_esrl.data.exact_ratio` (``ExactRatioSampler``, ``ExactRatioStorage``,
``ratio_counts``, importable from here too).
"""
from __future__ import annotations

import json
import math
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path

import torch
from tensordict import LazyStackedTensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, ReplayBufferEnsemble, TensorDictReplayBuffer

from torchrl_esrl.data.exact_ratio import ExactRatioSampler, ExactRatioStorage, ratio_counts
from torchrl_esrl.errors import ConfigError
from torchrl_esrl.run.capacity import Holding, bytes_per_transition
from torchrl_esrl.run.implementation import chosen_pieces
from torchrl_esrl.torchrl_private import append_rows

__all__ = ["BUFFER_NAMES", "TRANSITION_KEYS", "ExactRatioSampler", "ExactRatioStorage", "MultiBuffer", "make_buffer", "ratio_counts", "validate_ratio"]

BUFFER_NAMES = ("good", "bad", "noisy")

# Keys of a transition as TD3Loss (and any TorchRL off-policy loss) reads it. Both sources,
# the ES collector and TorchRL's Collector, carry extra keys of their own; keeping one key
# set makes batches from different buffers concatenable.
TRANSITION_KEYS = (
    "observation",
    "action",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
    ("next", "truncated"),
)


def validate_ratio(ratio: Sequence[float], field: str = "buffer.ratio") -> tuple[float, ...]:
    """Check a ratio of three non-negative numbers with a positive sum; one-line ConfigError otherwise."""
    try:
        values = tuple(float(r) for r in ratio)
    except (TypeError, ValueError):
        raise ConfigError(f"{field}: {ratio!r} is not a list of numbers (allowed: three non-negative numbers with a positive sum, e.g. [0.5,0.2,0.3])") from None
    if len(values) != len(BUFFER_NAMES) or any(not math.isfinite(r) or r < 0 for r in values) or sum(values) <= 0:
        raise ConfigError(f"{field}: {list(ratio)} is invalid (allowed: three non-negative numbers with a positive sum, e.g. [0.5,0.2,0.3])")
    return values


def make_buffer(capacity: int, device: str | torch.device = "cpu") -> TensorDictReplayBuffer:
    """One uniform-sampling TorchRL buffer over a preallocated (lazy) tensor storage."""
    return TensorDictReplayBuffer(storage=LazyTensorStorage(int(capacity), device=device))


class MultiBuffer(ReplayBufferEnsemble):
    """Three TorchRL replay buffers sampled at an exact ratio, as one TorchRL replay buffer.

    Args:
        ratio: shares of (good, bad, noisy) in every batch; normalised internally.
        capacity: capacity of each buffer (an int for all, or a mapping name -> int).
        batch_size: default size of :meth:`sample`.
        min_size: K of the paper; a buffer with a non-zero share is *ready* once it holds K items.
        renormalize: if False (the paper), sampling waits until every buffer with a non-zero
            share is ready. If True, sampling starts as soon as one is, with the ratio
            renormalised over the ready buffers.
        buffers: existing buffers by name (built with :func:`make_buffer` otherwise).
        keys: keys stored from each transition (None keeps all keys as given).
        default: buffer that :meth:`extend` writes to when it is given no name and no tags
            (what a TorchRL ``Collector(..., replay_buffer=mb)`` writes lands there).
        source_key: key of the per-item buffer index in sampled batches.
        device: device of the buffers' storages (when built here).
        direct_writes: write each batch into the storage one tensor copy per key where the
            buffer is the plain layout of :func:`make_buffer` (what ``extend`` writes,
            ``torchrl_esrl.torchrl_private.append_rows``); False (the reference): TorchRL's
            ``extend`` for every write.
        direct_reads: gather sampled items straight from the storages' tensors
            (:class:`ExactRatioStorage`); False (the reference): each buffer's storage ``get``.
    """

    def __init__(
        self,
        ratio: Sequence[float] = (0.5, 0.2, 0.3),
        capacity: int | Mapping[str, int] = 1_000_000,
        batch_size: int = 256,
        min_size: int = 0,
        renormalize: bool = False,
        buffers: Mapping[str, TensorDictReplayBuffer] | None = None,
        names: Sequence[str] = BUFFER_NAMES,
        keys: Sequence | None = TRANSITION_KEYS,
        default: str = "noisy",
        source_key: str = "buffer",
        device: str | torch.device = "cpu",
        direct_writes: bool = False,
        direct_reads: bool = False,
    ):
        names = tuple(names)
        ratio = validate_ratio(ratio) if len(names) == 3 else tuple(float(r) for r in ratio)
        if buffers is None:
            caps = capacity if isinstance(capacity, Mapping) else {n: capacity for n in names}
            buffers = {n: make_buffer(caps[n], device) for n in names}
        if tuple(buffers) != names:
            raise ValueError(f"buffers must be named {names}, got {tuple(buffers)}")
        if default not in names:
            raise ValueError(f"default must be one of {names}, got {default!r}")
        members = tuple(buffers.values())
        stack = LazyStackedTensorDict.maybe_dense_stack  # what ReplayBufferEnsemble's indexing collates with
        super().__init__(*members, batch_size=int(batch_size), collate_fn=stack)
        # Swap in the exact-ratio sampler and the flat-batch storage ensemble over the same members.
        self.set_sampler(ExactRatioSampler(*(b.sampler for b in members), ratio=ratio, min_size=min_size, renormalize=renormalize))
        storage = ExactRatioStorage(*(b.storage for b in members), transforms=[b.transform for b in members], source_key=source_key, direct_reads=direct_reads)
        self.set_storage(storage, collate_fn=stack)
        storage.attach(self)
        self.set_writer(self.writer)  # registers the writers with the new storage ensemble
        self.names = names
        self.buffers = dict(buffers)
        self.keys = None if keys is None else tuple(keys)
        self.default = default
        self.source_key = source_key
        self.device = torch.device(device)
        self.direct_writes = bool(direct_writes)

    # ------------------------------------------------------------ settings
    ratio = property(lambda self: self.sampler.ratio, lambda self, value: setattr(self.sampler, "ratio", tuple(float(r) for r in value)))
    min_size = property(lambda self: self.sampler.min_size, lambda self, value: setattr(self.sampler, "min_size", int(value)))
    renormalize = property(lambda self: self.sampler.renormalize, lambda self, value: setattr(self.sampler, "renormalize", bool(value)))

    # ----------------------------------------------------------------- access
    def __getitem__(self, name):
        """A named buffer (``mb["good"]``); other indices as on ``ReplayBufferEnsemble``."""
        if isinstance(name, str):
            return self.buffers[name]
        return super().__getitem__(name)

    def __getattr__(self, name: str) -> TensorDictReplayBuffer:
        buffers = self.__dict__.get("buffers", {})
        if name in buffers:
            return buffers[name]
        raise AttributeError(name)

    def __len__(self) -> int:
        return sum(len(b) for b in self.buffers.values())

    def sizes(self) -> dict[str, int]:
        return {n: len(b) for n, b in self.buffers.items()}

    def __repr__(self) -> str:
        shares = ", ".join(f"{n}={r:g}" for n, r in zip(self.names, self.ratio))
        return f"MultiBuffer(ratio=({shares}), sizes={self.sizes()}, min_size={self.min_size}, renormalize={self.renormalize})"

    # ------------------------------------------------------------------ write
    def extend(self, data: TensorDictBase, name: str | None = None, **kwargs):
        """Write transitions to buffer ``name``; without one, route by ``data[source_key]`` if
        present (items tagged as :meth:`sample` tags them), else write to ``default``.

        Routing is done here rather than by ``ReplayBufferEnsemble(routing_key=...)``: TorchRL's
        routed write stores the routing key with the data, while each buffer keeps only ``keys``.
        """
        if data.batch_size.numel() == 0:  # TensorDict.numel() is 1 for an empty batch
            return None
        if name is None and self.source_key in data.keys():
            source = data.get(self.source_key).reshape(-1)
            flat = data.reshape(-1)
            for index, buffer_name in enumerate(self.names):
                mask = source == index
                if mask.any():
                    self.extend(flat[mask], buffer_name)
            return None
        buffer = self.buffers[name if name is not None else self.default]
        # One copy per stored key into the storage (what extend writes, tests/test_torchrl_private.py);
        # extend itself for a first write, a batch of another shape, or a buffer layout append_rows
        # does not cover (it declines those).
        index = append_rows(buffer, data, self.keys) if self.direct_writes and not kwargs else None
        if index is None:
            index = buffer.extend((data if self.keys is None else data.select(*self.keys)).reshape(-1), **kwargs)
        return index

    add = extend

    # ------------------------------------------------------------------- read
    def ready_names(self) -> list[str]:
        """Buffers with a non-zero share that hold at least ``min_size`` (and one) items."""
        return [n for n, ready in zip(self.names, self.sampler.ready_members(self.storage)) if ready]

    def ready(self) -> bool:
        """Paper's rule: every buffer with a non-zero share holds K items (any one, if renormalising)."""
        return self.sampler.ready(self.storage)

    def effective_ratio(self) -> tuple[float, ...]:
        """The ratio actually sampled: the configured one, restricted to ready buffers if renormalising."""
        return self.sampler.effective_ratio(self.storage)

    def counts(self, batch_size: int | None = None) -> dict[str, int]:
        """How many items of each buffer a batch of ``batch_size`` holds."""
        batch_size = self.batch_size if batch_size is None else int(batch_size)
        return dict(zip(self.names, self.sampler.counts(self.storage, batch_size)))

    def sample(self, batch_size: int | None = None, return_info: bool = False):
        """A batch with exactly each buffer's share, tagged under ``source_key``: the stored keys
        (``keys`` and TorchRL's per-item ``"index"`` in its buffer) plus the tag.

        TorchRL's ``ReplayBuffer.sample`` steps, as public calls: the sampler picks indices, the
        storage gathers them, the buffer's transform (if any) runs. ``ReplayBufferEnsemble``'s own
        step would stack equal sub-batches; here the storage returns one flat batch.
        """
        batch_size = self.batch_size if batch_size is None else int(batch_size)
        index, info = self.sampler.sample(self.storage, batch_size)  # raises if not ready()
        batch = self.storage.get(index)  # tags each item under source_key
        transform = self.transform
        if transform is not None and len(transform):
            batch = transform(batch)
        if return_info:
            info["index"] = index
            return batch, info
        return batch

    # ------------------------------------------------------------ persistence
    def state_dict(self) -> dict:
        return {
            "ratio": list(self.ratio),
            "min_size": self.min_size,
            "renormalize": self.renormalize,
            "buffers": {n: b.state_dict() for n, b in self.buffers.items()},
        }

    def load_state_dict(self, state: Mapping) -> None:
        self.ratio = tuple(state["ratio"])
        self.min_size = int(state["min_size"])
        self.renormalize = bool(state["renormalize"])
        for name, buffer_state in state["buffers"].items():
            self.buffers[name].load_state_dict(buffer_state)

    def dumps(self, path: str | Path) -> None:
        """Write every non-empty buffer with TorchRL's own ``dumps`` into ``path/<name>``, plus
        ``multibuffer.json`` (settings and the names of the empty buffers, which TorchRL cannot dump)."""
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        empty = [name for name, buffer in self.buffers.items() if len(buffer) == 0]
        for name, buffer in self.buffers.items():
            if name not in empty:
                buffer.dumps(path / name)
        meta = {"names": list(self.names), "ratio": list(self.ratio), "min_size": self.min_size, "renormalize": self.renormalize, "empty": empty}
        (path / "multibuffer.json").write_text(json.dumps(meta, indent=2))

    def loads(self, path: str | Path) -> MultiBuffer:
        path = Path(path)
        meta = json.loads((path / "multibuffer.json").read_text())
        if tuple(meta["names"]) != self.names:
            raise ValueError(f"{path}: buffers {meta['names']} do not match {list(self.names)}")
        self.ratio, self.min_size, self.renormalize = tuple(meta["ratio"]), int(meta["min_size"]), bool(meta["renormalize"])
        for name, buffer in self.buffers.items():
            if name in meta.get("empty", ()):
                buffer.empty()
            else:
                buffer.loads(path / name)
        return self


def make_multibuffer(cfg, pieces: Collection[str] | None = None, one_buffer: bool = False) -> MultiBuffer:
    """The good/bad/noisy MultiBuffer of the ``buffer`` section, with the fast pieces chosen
    (:mod:`torchrl_esrl.run.implementation`); ``buffer.mode=shared`` gives one buffer for
    everything (ERL-style ablation: ``ratio=(0, 0, 1)``, ES transitions are written to it too), as
    does ``one_buffer`` (the TD3 and CEM-RL baselines' replay buffer)."""
    c, fast = cfg.buffer, chosen_pieces(cfg, pieces)
    shared = one_buffer or c.mode == "shared"
    return MultiBuffer(
        ratio=[0.0, 0.0, 1.0] if shared else list(c.ratio),
        capacity=c.capacity,
        batch_size=c.batch_size,
        min_size=c.min_size,
        renormalize=c.renormalize and not one_buffer,
        device=cfg.device,
        direct_writes="buffer_writes" in fast,
        direct_reads="buffer_reads" in fast,
    )


def buffer_holdings(cfg, sizes, buffers: int) -> list[Holding]:
    """``buffers`` replay buffers of ``buffer.capacity`` transitions each (:func:`make_multibuffer`
    with its three buffers, or ``buffers=1`` with one), on ``device``, for the run's memory
    estimate (:mod:`torchrl_esrl.run.capacity`)."""
    size = buffers * int(cfg.buffer.capacity) * bytes_per_transition(sizes.observation_dim, sizes.action_dim)
    return [Holding("buffers", size, "buffer.capacity", on_device=True)]
