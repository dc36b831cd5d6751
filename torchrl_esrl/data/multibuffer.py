"""The MultiBuffer of ES-TD3Buffers (paper, Section 3.1 "Multi-Buffers", and Algorithm 1).

Three named TorchRL :class:`~torchrl.data.TensorDictReplayBuffer` s, ``good``, ``bad`` and
``noisy``, composed into one TorchRL :class:`~torchrl.data.ReplayBufferEnsemble` (so a
MultiBuffer *is* a :class:`~torchrl.data.ReplayBuffer`: a TorchRL ``Collector`` or ``Trainer``
can write to it and a TorchRL loss learn from its batches). Every batch holds *exactly* each
buffer's share of a fixed ratio (a:b:c), by largest-remainder rounding, and every item is tagged
with the index of the buffer it came from under ``source_key``.

TorchRL's own :class:`~torchrl.data.replay_buffers.SamplerEnsemble` takes equal sub-batches or
draws buffers at random with weights ``p`` (a ratio held only in expectation). The custom parts
are :class:`ExactRatioSampler` (a ``SamplerEnsemble`` asking each member's own sampler for its
exact count) and :class:`ExactRatioStorage` (a ``StorageEnsemble`` that gathers those items
into one flat batch).
"""
from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from tensordict import LazyStackedTensorDict, TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, ReplayBufferEnsemble, TensorDictReplayBuffer
from torchrl.data.replay_buffers import SamplerEnsemble, StorageEnsemble

from torchrl_esrl.arrays import numpy_views
from torchrl_esrl.errors import ConfigError
from torchrl_esrl.torchrl_private import append_rows, tensor_storage_data, unchecked_tensordict

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


def _members(storage: StorageEnsemble) -> tuple:
    """The member storages of a ``StorageEnsemble`` (public indexing; cached by ours)."""
    members = getattr(storage, "members", None)
    return members if members is not None else tuple(storage[i] for i in range(len(storage)))


class ExactRatioSampler(SamplerEnsemble):
    """A ``SamplerEnsemble`` whose batches hold exactly each member's share (paper, Section 3.1).

    Each member's own sampler (``RandomSampler`` for :func:`make_buffer`'s buffers) draws
    ``ratio_counts(batch_size, ratio)[i]`` indices from its storage. The readiness rule lives
    here too: a member with a non-zero share is *ready* once it holds ``min_size`` (K) items;
    sampling needs all of them ready, or, with ``renormalize``, any one, the ratio then being
    renormalised over the ready ones.

    ``sample`` returns ``(index, info)`` with ``index`` a TensorDict of batch ``[batch_size]``:
    ``"buffer_ids"`` (each item's member, in member order) and ``"index"`` (its index in that
    member's storage), the layout :meth:`ExactRatioStorage.get` reads. Extra info of the member
    samplers (priority weights...) is not returned.
    """

    def __init__(self, *samplers, ratio: Sequence[float], min_size: int = 0, renormalize: bool = False):
        super().__init__(*samplers, sample_from_all=True)
        if len(ratio) != len(samplers):
            raise ValueError(f"one share per sampler: {len(samplers)} samplers, ratio {list(ratio)}")
        self.members = tuple(samplers)
        self.ratio = tuple(float(r) for r in ratio)
        self.min_size = int(min_size)
        self.renormalize = bool(renormalize)
        self._counts_cache: dict = {}
        self._ids_cache: dict = {}

    # Each rule below reads the members' sizes once (``len`` of a TorchRL storage is a
    # compile-guarded call, and sampling is on the hot path of every TD3 update).
    def _ready_members(self, sizes: Sequence[int]) -> list[bool]:
        need = max(self.min_size, 1)
        return [r > 0 and size >= need for r, size in zip(self.ratio, sizes)]

    def _ready(self, sizes: Sequence[int]) -> bool:
        shared = [ready for r, ready in zip(self.ratio, self._ready_members(sizes)) if r > 0]
        return any(shared) if self.renormalize else all(shared)

    def _effective_ratio(self, sizes: Sequence[int]) -> tuple[float, ...]:
        if not self.renormalize:
            return self.ratio
        return tuple(r if ready else 0.0 for r, ready in zip(self.ratio, self._ready_members(sizes)))

    def _counts(self, sizes: Sequence[int], batch_size: int) -> tuple[int, ...]:
        """``ratio_counts`` of the effective ratio, memoised (it sorts in Python)."""
        key = (int(batch_size), self._effective_ratio(sizes))
        counts = self._counts_cache.get(key)
        if counts is None:
            counts = self._counts_cache[key] = tuple(ratio_counts(*key))
        return counts

    @staticmethod
    def sizes(storage: StorageEnsemble) -> list[int]:
        return [len(member) for member in _members(storage)]

    def ready_members(self, storage: StorageEnsemble) -> list[bool]:
        """Per member: has a non-zero share and holds at least ``min_size`` (and one) items."""
        return self._ready_members(self.sizes(storage))

    def ready(self, storage: StorageEnsemble) -> bool:
        """Every member with a share is ready (any one, if renormalising)."""
        return self._ready(self.sizes(storage))

    def can_sample(self, storage: StorageEnsemble, batch_size: int | None = None) -> bool:
        return self.ready(storage)

    def effective_ratio(self, storage: StorageEnsemble) -> tuple[float, ...]:
        """The configured ratio; restricted to the ready members when renormalising."""
        return self._effective_ratio(self.sizes(storage))

    def counts(self, storage: StorageEnsemble, batch_size: int) -> tuple[int, ...]:
        """Items of each member in a batch of ``batch_size``."""
        return self._counts(self.sizes(storage), batch_size)

    def sample(self, storage: StorageEnsemble, batch_size: int) -> tuple[TensorDict, dict]:
        members = _members(storage)
        sizes = [len(member) for member in members]
        if not self._ready(sizes):
            raise RuntimeError(f"not ready to sample: sizes {sizes}, ratio {list(self.ratio)}, min_size {self.min_size}, renormalize {self.renormalize}")
        counts = self._counts(sizes, batch_size)
        parts = [sampler.sample(member, count)[0] for sampler, member, count in zip(self.members, members, counts) if count]
        index = torch.cat(parts) if len(parts) > 1 else parts[0]
        ids = self._ids_cache.get(counts)
        if ids is None:
            ids = self._ids_cache[counts] = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts)).to(index.device)
        return unchecked_tensordict({"buffer_ids": ids.clone(), "index": index}, torch.Size([int(batch_size)]), None), {}


def _nest(flat: Mapping) -> dict:
    """``{("next", "reward"): t}`` -> ``{"next": {"reward": t}}`` (one TensorDict built from a
    nested dict costs about 2/3 of setting its keys one by one)."""
    nested: dict = {}
    for key, value in flat.items():
        path = key if isinstance(key, tuple) else (key,)
        node = nested
        for part in path[:-1]:
            node = node.setdefault(part, {})
        node[path[-1]] = value
    return nested


class ExactRatioStorage(StorageEnsemble):
    """A ``StorageEnsemble`` whose :meth:`get` returns one flat batch, in the order of the index.

    ``StorageEnsemble.get`` returns a list of ``(buffer_id, data)``, one per sub-batch, for
    ``ReplayBufferEnsemble`` to stack; the MultiBuffer's sub-batches differ in size, and a TorchRL
    loss wants one flat batch. Here each item's member is written under ``source_key`` instead.

    The reference reads each member's items with its public ``get`` and concatenates the parts.
    With ``direct_reads``, where every member is a tensor storage without transform holding the
    same keys, the items are copied straight from the storages' tensors into one preallocated
    batch (one gather per key and member); both give the same batch (``tests/test_multibuffer.py``).
    """

    def __init__(self, *storages, transforms: list | None = None, source_key: str | None = None, direct_reads: bool = False):
        super().__init__(*storages, transforms=transforms)
        self.direct_reads = bool(direct_reads)
        self.members = tuple(storages)
        self.member_transforms = tuple(transforms) if transforms is not None else (None,) * len(storages)
        self.source_key = source_key
        self._leaves_cache: tuple | None = None

    def fast_path(self) -> bool:
        """Whether :meth:`get` copies straight from the storages' tensors (else: members' ``get``)."""
        return self.direct_reads and self._leaves() is not None

    def _leaves(self) -> tuple | None:
        """``(keys, per member: its storage's tensor of each key, None for an empty member)``, or
        None when the fast path does not apply. Cached while every member keeps its TensorDict."""
        if any(t is not None and len(t) for t in self.member_transforms):
            return None
        datas = tuple(tensor_storage_data(m) for m in self.members)
        cached = self._leaves_cache
        if cached is not None and all(a is b for a, b in zip(cached[0], datas)):
            return cached[1]
        written = [d for d in datas if d is not None]
        if not written or any(d is None and len(m) for d, m in zip(datas, self.members)):
            return None
        keys = tuple(written[0].keys(include_nested=True, leaves_only=True))
        reference = [written[0].get(k) for k in keys]
        leaves = []
        for data in datas:
            if data is None:
                leaves.append(None)
                continue
            if set(data.keys(include_nested=True, leaves_only=True)) != set(keys):
                return None
            tensors = tuple(data.get(k) for k in keys)
            if any(t.dtype != r.dtype or t.shape[1:] != r.shape[1:] or t.device != r.device for t, r in zip(tensors, reference)):
                return None
            leaves.append(tensors)
        # numpy views of every member's tensors (CPU storages), for the gather in get()
        arrays = [None if tensors is None else numpy_views(tensors) for tensors in leaves]
        arrays = None if any(a is None for a, t in zip(arrays, leaves) if t is not None) else arrays
        self._leaves_cache = (datas, (keys, leaves, arrays))
        return self._leaves_cache[1]

    def get(self, item: TensorDictBase) -> TensorDictBase:
        """The items ``item["index"]`` of members ``item["buffer_ids"]`` as one TensorDict."""
        buffer_ids, index = item.get("buffer_ids"), item.get("index")
        members, counts = torch.unique_consecutive(buffer_ids, return_counts=True)
        groups, start = [], 0  # (member, its indices, position in the batch): runs of one member
        for member, count in zip(members.tolist(), counts.tolist()):
            groups.append((member, index[start : start + count], start))
            start += count
        leaves = self._leaves() if self.direct_reads else None
        if leaves is None:
            parts = []
            for member, member_index, _ in groups:
                part = self.members[member].get(member_index)
                if isinstance(part, list):  # a ListStorage gives its items as a list
                    part = torch.stack(part)
                transform = self.member_transforms[member]
                parts.append(transform(part) if transform is not None and len(transform) else part)
            batch = torch.cat(parts, 0)
            if self.source_key is not None:
                batch.set(self.source_key, buffer_ids)
            return batch
        keys, tensors, arrays = leaves
        total = buffer_ids.numel()
        outs = {}
        # CPU storages: numpy's take, without torch.index_select's dispatch; the same rows, copied exactly.
        member_indices = None if arrays is None else numpy_views(member_index for _, member_index, _ in groups)
        for position, key in enumerate(keys):
            reference = tensors[groups[0][0]][position]
            out = outs[key] = torch.empty((total, *reference.shape[1:]), dtype=reference.dtype, device=reference.device)
            if member_indices is None:
                for member, member_index, begin in groups:
                    torch.index_select(tensors[member][position], 0, member_index, out=out[begin : begin + member_index.numel()])
                continue
            out_array = out.numpy()
            for (member, _, begin), member_index in zip(groups, member_indices):
                arrays[member][position].take(member_index, 0, out_array[begin : begin + len(member_index)])
        if self.source_key is not None:
            outs[self.source_key] = buffer_ids
        # Leaves made here to fit the batch: the constructor's per-leaf checks are skipped.
        return unchecked_tensordict(_nest(outs), torch.Size([total]), None)


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
