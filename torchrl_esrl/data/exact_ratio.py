"""The exact-ratio sampling of the MultiBuffer (paper, Section 3.1 "Multi-Buffers").

TorchRL's own :class:`~torchrl.data.replay_buffers.SamplerEnsemble` takes equal sub-batches or
draws buffers at random with weights ``p`` (a ratio held only in expectation). Here
:class:`ExactRatioSampler` (a ``SamplerEnsemble``) asks each member's own sampler for its exact
count, :func:`ratio_counts`, and :class:`ExactRatioStorage` (a ``StorageEnsemble``) gathers those
items into one flat batch, each tagged with its member. :class:`~torchrl_esrl.data.multibuffer.MultiBuffer`
composes them over its three buffers.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data.replay_buffers import SamplerEnsemble, StorageEnsemble

from torchrl_esrl.arrays import numpy_views
from torchrl_esrl.torchrl_private import tensor_storage_data, unchecked_tensordict


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
    batch (one gather per key and member); both give the same batch (``tests/test_exact_ratio.py``).
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
