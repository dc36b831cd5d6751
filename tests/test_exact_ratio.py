"""The exact-ratio sampler and storage ensemble (torchrl_esrl/data/exact_ratio.py); the MultiBuffer
that composes them is tested in tests/test_multibuffer.py."""
import doctest

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer

from torchrl_esrl import MultiBuffer
from torchrl_esrl.data import exact_ratio
from torchrl_esrl.data.exact_ratio import ratio_counts

from conftest import transitions


def test_the_docstring_examples_hold():
    result = doctest.testmod(exact_ratio)
    assert result.attempted > 0 and result.failed == 0


@pytest.mark.parametrize(
    "batch, ratio, expected",
    [
        (256, (0.5, 0.2, 0.3), [128, 51, 77]),
        (256, (0.34, 0.33, 0.33), [87, 85, 84]),
        (100, (1, 1, 1), [34, 33, 33]),
        (10, (0, 0, 1), [0, 0, 10]),
        (7, (0.5, 0.5, 0), [4, 3, 0]),
        (1, (0.2, 0.3, 0.5), [0, 0, 1]),
        (255, (5, 2, 3), [128, 51, 76]),
    ],
)
def test_ratio_counts_largest_remainder(batch, ratio, expected):
    counts = ratio_counts(batch, ratio)
    assert counts == expected
    assert sum(counts) == batch


def test_ratio_counts_are_within_one_of_the_quota():
    generator = torch.Generator().manual_seed(1)
    for _ in range(200):
        ratio = torch.rand(3, generator=generator).tolist()
        batch = int(torch.randint(1, 1000, (1,), generator=generator))
        counts = ratio_counts(batch, ratio)
        assert sum(counts) == batch
        for count, share in zip(counts, ratio):
            assert abs(count - batch * share / sum(ratio)) < 1


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])  # numpy's take; torch's index_select (no numpy bfloat16)
def test_fast_gather_equals_each_buffers_own_storage_get(dtype):
    """The fast path (a gather from the storages' tensors) returns what each buffer's public
    ``storage.get`` returns for the same indices, tags included, in any order of buffer ids."""
    buffer = MultiBuffer(capacity=100, direct_reads=True)
    generator = torch.Generator().manual_seed(0)
    for name, size in zip(buffer.names, (40, 70, 100)):
        data = transitions(size)
        data["observation"] = torch.randn(size, 3, generator=generator).to(dtype)
        buffer.extend(data, name)
    assert (buffer.storage._leaves()[2] is None) == (dtype is torch.bfloat16)  # numpy views of the storages, or none
    ids = torch.tensor([2, 0, 0, 1, 2, 0, 1, 1, 2])
    local = torch.tensor([99, 3, 39, 0, 5, 7, 69, 2, 0])
    index = TensorDict({"buffer_ids": ids, "index": local}, batch_size=[len(ids)])
    assert buffer.storage.fast_path()
    batch = buffer.storage.get(index)
    for position, (member, item) in enumerate(zip(ids.tolist(), local.tolist())):
        expected = buffer[member].storage.get(torch.tensor([item]))[0]
        got = batch[position]
        assert got["buffer"] == member
        for key in expected.keys(include_nested=True, leaves_only=True):
            assert torch.equal(got[key], expected[key]), key


def test_members_get_path_when_storages_are_not_tensor_storages():
    """Buffers over TorchRL ``ListStorage`` (no tensors to gather from) take each buffer's
    ``get`` and still give exact counts and tags."""
    from torchrl.data import ListStorage

    buffers = {name: TensorDictReplayBuffer(storage=ListStorage(100)) for name in ("good", "bad", "noisy")}
    buffer = MultiBuffer(ratio=(0.5, 0.2, 0.3), buffers=buffers, batch_size=50)
    for index, name in enumerate(buffer.names):
        buffer.extend(transitions(20, fill=float(index)), name)
    assert not buffer.storage.fast_path()
    batch = buffer.sample()
    assert torch.bincount(batch["buffer"], minlength=3).tolist() == ratio_counts(50, (0.5, 0.2, 0.3))
    assert torch.equal(batch["observation"][:, 0], batch["buffer"].float())
