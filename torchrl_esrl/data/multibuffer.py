"""The MultiBuffer of ES-TD3Buffers (paper, Section 4.1 "Multi-Buffers" and Algorithm 1).

Three named TorchRL :class:`~torchrl.data.TensorDictReplayBuffer` s, ``good``, ``bad`` and
``noisy``, sampled at a fixed ratio (a:b:c). Every batch holds *exactly* each buffer's share
(largest-remainder rounding), and every item is tagged with the index of the buffer it came
from under ``source_key``. TorchRL's ``ReplayBufferEnsemble`` honours a ratio only in
expectation, hence this class.

The MultiBuffer is a drop-in replay buffer for other TorchRL code: ``extend``, ``sample``,
``len``, ``state_dict``/``load_state_dict`` and ``dumps``/``loads`` behave as on a
``TensorDictReplayBuffer``.
"""
from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictReplayBuffer

from torchrl_esrl.errors import ConfigError

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


def ratio_counts(batch_size: int, ratio: Sequence[float]) -> list[int]:
    """Split ``batch_size`` by ``ratio`` exactly, with largest-remainder (Hamilton) rounding.

    >>> ratio_counts(256, (0.5, 0.2, 0.3))
    [128, 51, 77]

    Ties in the remainders go to the earlier buffer, so the result is deterministic.
    """
    total = float(sum(ratio))
    if batch_size < 0 or total <= 0 or any(r < 0 for r in ratio):
        raise ValueError(f"ratio_counts needs batch_size >= 0 and a non-negative ratio with positive sum, got {batch_size}, {list(ratio)}")
    quotas = [batch_size * r / total for r in ratio]
    counts = [math.floor(q) for q in quotas]
    left = batch_size - sum(counts)
    order = sorted(range(len(ratio)), key=lambda i: (-(quotas[i] - counts[i]), i))
    for i in order[:left]:
        counts[i] += 1
    return counts


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


class MultiBuffer:
    """Three TorchRL replay buffers sampled at an exact ratio.

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
        default: buffer that :meth:`extend` writes to when it is given no name.
        source_key: key of the per-item buffer index in sampled batches.
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
    ):
        self.names = tuple(names)
        self.ratio = validate_ratio(ratio) if len(self.names) == 3 else tuple(float(r) for r in ratio)
        if buffers is None:
            caps = capacity if isinstance(capacity, Mapping) else {n: capacity for n in self.names}
            buffers = {n: make_buffer(caps[n], device) for n in self.names}
        if tuple(buffers) != self.names:
            raise ValueError(f"buffers must be named {self.names}, got {tuple(buffers)}")
        self.buffers = dict(buffers)
        self.batch_size = int(batch_size)
        self.min_size = int(min_size)
        self.renormalize = bool(renormalize)
        self.keys = None if keys is None else tuple(keys)
        if default not in self.names:
            raise ValueError(f"default must be one of {self.names}, got {default!r}")
        self.default = default
        self.source_key = source_key

    # ----------------------------------------------------------------- access
    def __getitem__(self, name: str) -> TensorDictReplayBuffer:
        return self.buffers[name]

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
    def extend(self, data: TensorDictBase, name: str | None = None) -> None:
        """Write transitions to buffer ``name``; without one, route by ``data[source_key]`` if
        present (items tagged as :meth:`sample` tags them), else write to ``default``."""
        if data.batch_size.numel() == 0:  # TensorDict.numel() is 1 for an empty batch
            return
        if name is None and self.source_key in data.keys():
            source = data.get(self.source_key).reshape(-1)
            flat = data.reshape(-1)
            for index, buffer_name in enumerate(self.names):
                mask = source == index
                if mask.any():
                    self.extend(flat[mask], buffer_name)
            return
        name = self.default if name is None else name
        if self.keys is not None:
            data = data.select(*self.keys)
        self.buffers[name].extend(data.reshape(-1))

    add = extend

    # ------------------------------------------------------------------- read
    def ready_names(self) -> list[str]:
        """Buffers with a non-zero share that hold at least ``min_size`` (and one) items."""
        need = max(self.min_size, 1)
        return [n for n, r in zip(self.names, self.ratio) if r > 0 and len(self.buffers[n]) >= need]

    def ready(self) -> bool:
        """Paper's rule: every buffer with a non-zero share holds K items (any one, if renormalising)."""
        need = max(self.min_size, 1)
        shared = [len(b) >= need for b, r in zip(self.buffers.values(), self.ratio) if r > 0]
        return any(shared) if self.renormalize else all(shared)

    def effective_ratio(self) -> tuple[float, ...]:
        """The ratio actually sampled: the configured one, restricted to ready buffers if renormalising."""
        if not self.renormalize:
            return self.ratio
        ready = set(self.ready_names())
        return tuple(r if n in ready else 0.0 for n, r in zip(self.names, self.ratio))

    def counts(self, batch_size: int | None = None) -> dict[str, int]:
        """How many items of each buffer a batch of ``batch_size`` holds."""
        batch_size = self.batch_size if batch_size is None else int(batch_size)
        return dict(zip(self.names, self._counts(batch_size, self.effective_ratio())))

    def _counts(self, batch_size: int, ratio: tuple[float, ...]) -> tuple[int, ...]:
        """``ratio_counts`` memoised (it sorts in Python: ~10 us a call, paid on every sample)."""
        key = (batch_size, ratio)
        cache = self.__dict__.setdefault("_counts_cache", {})
        if key not in cache:
            cache[key] = tuple(ratio_counts(batch_size, ratio))
        return cache[key]

    def sample(self, batch_size: int | None = None) -> TensorDict:
        """A batch with exactly each buffer's share, tagged under ``source_key``."""
        if not self.ready():
            raise RuntimeError(f"MultiBuffer is not ready to sample: {self!r}")
        batch_size = self.batch_size if batch_size is None else int(batch_size)
        counts = self._counts(batch_size, self.effective_ratio())
        leaves = self._gather_leaves()
        if leaves is not None:
            return self._gather(counts, leaves)
        parts, sources = [], []
        for index, (name, count) in enumerate(zip(self.names, counts)):
            if count == 0:
                continue
            part = self.buffers[name].sample(count)
            if self.keys is not None:
                part = part.select(*self.keys)
            parts.append(part)
            sources.append(torch.full((count,), index, dtype=torch.long))
        batch = torch.cat(parts, 0)
        batch.set(self.source_key, torch.cat(sources))
        return batch

    def _can_gather(self) -> bool:
        """True when every buffer is a plain uniform TorchRL buffer over a tensor storage."""
        return self.keys is not None and all(
            isinstance(b._storage, LazyTensorStorage)
            and type(b._sampler) is RandomSampler
            and len(b._transform) == 0
            and (len(b) == 0 or b._storage.initialized)
            for b in self.buffers.values()
        )

    def _gather_leaves(self) -> list[tuple] | None:
        """Per buffer, the storage's tensor of every key (None: use the ``sample()`` path).

        Checking ``_can_gather`` and looking the nested keys up in three storages cost more than
        the gather itself (~100 us of Python a batch, measured), so both are cached while every
        buffer keeps the same storage TensorDict, sampler and transform count."""
        state = tuple((b._storage, getattr(b._storage, "_storage", None), b._sampler, len(b._transform)) for b in self.buffers.values())
        cached = self.__dict__.get("_leaves_cache")
        if cached is not None and len(cached[0]) == len(state) and all(
            x is y for old, new in zip(cached[0], state) for x, y in zip(old[:3], new[:3])
        ) and all(old[3] == new[3] for old, new in zip(cached[0], state)):
            return cached[1]
        if not self._can_gather():
            return None
        if any(s[1] is None for s in state):  # a storage not written yet
            return [None if s[1] is None else tuple(s[1].get(k) for k in self.keys) for s in state]
        leaves = [tuple(s[1].get(k) for k in self.keys) for s in state]
        self.__dict__["_leaves_cache"] = (state, leaves)
        return leaves

    def _gather(self, counts: Sequence[int], leaves: list[tuple]) -> TensorDict:
        """Uniform sampling with replacement, as TorchRL's ``RandomSampler``, written by hand:
        one ``index_select`` per key straight from each buffer's storage into a preallocated
        batch. Three ``sample()`` calls and a ``torch.cat`` measured ~3x one buffer's sample;
        this path measures about the same as one (benchmarks/buffer_sampling.py)."""
        total = sum(counts)
        picks = []  # (storage tensors, indices, start)
        start = 0
        for buffer, count, tensors in zip(self.buffers.values(), counts, leaves):
            if count:
                picks.append((tensors, torch.randint(len(buffer), (count,)), start))
                start += count
        batch = TensorDict(batch_size=[total])
        for position, key in enumerate(self.keys):
            reference = picks[0][0][position]
            out = torch.empty((total, *reference.shape[1:]), dtype=reference.dtype, device=reference.device)
            for tensors, index, begin in picks:
                torch.index_select(tensors[position], 0, index, out=out[begin : begin + index.numel()])
            batch.set(key, out)
        sources = self.__dict__.setdefault("_sources_cache", {})
        if counts not in sources:
            sources[counts] = torch.repeat_interleave(torch.arange(len(self.names)), torch.tensor(counts))
        batch.set(self.source_key, sources[counts].clone())
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
        self.__dict__.pop("_leaves_cache", None)  # storages may hold new tensors now
        for name, buffer_state in state["buffers"].items():
            self.buffers[name].load_state_dict(buffer_state)

    def dumps(self, path: str | Path) -> None:
        """Write every buffer with TorchRL's own ``dumps`` into ``path/<name>``, plus ``multibuffer.json``."""
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        for name, buffer in self.buffers.items():
            buffer.dumps(path / name)
        meta = {"names": list(self.names), "ratio": list(self.ratio), "min_size": self.min_size, "renormalize": self.renormalize}
        (path / "multibuffer.json").write_text(json.dumps(meta, indent=2))

    def loads(self, path: str | Path) -> MultiBuffer:
        path = Path(path)
        meta = json.loads((path / "multibuffer.json").read_text())
        if tuple(meta["names"]) != self.names:
            raise ValueError(f"{path}: buffers {meta['names']} do not match {list(self.names)}")
        self.ratio, self.min_size, self.renormalize = tuple(meta["ratio"]), int(meta["min_size"]), bool(meta["renormalize"])
        self.__dict__.pop("_leaves_cache", None)
        for name, buffer in self.buffers.items():
            buffer.loads(path / name)
        return self
