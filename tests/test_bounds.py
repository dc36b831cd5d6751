"""benchmarks.bounds: the matrix products it times are those the loop's TD3 update makes, and the ES chunk
it times is the one the batched backend plays."""
from collections import Counter

import torch
from torchrl.data import Bounded

from benchmarks import bounds
from benchmarks.common import transitions
from benchmarks.td3_update import FAST_TD3
from torchrl_esrl.modules.networks import make_actor, make_critic
from torchrl_esrl.objectives.td3 import TD3


PRODUCTS = {"aten::addmm", "aten::baddbmm", "aten::bmm", "aten::mm"}


def _products(run) -> Counter:
    """The matrix products ``run()`` makes: (op, its inputs' shapes) -> calls, from torch's profiler
    (torch's flop counter cannot be used: its module hooks make the fast loss hand over to TD3Loss)."""
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU], record_shapes=True) as profile:
        run()
    return Counter((event.name, str(event.input_shapes)) for event in profile.events() if event.name in PRODUCTS)


def test_the_products_timed_are_the_fast_updates_own_op_by_op():
    """The critic products twice and the actor products once (policy delay 2) of ``update_products``
    are the matrix products of two updates of TD3 with the fast pieces: the same ops on the same
    shapes, as many times."""
    obs_dim, act_dim, batch_size = 17, 6, 64
    critic_products, actor_products = bounds.update_products(obs_dim, act_dim, batch=batch_size)
    spec = Bounded(-torch.ones(act_dim), torch.ones(act_dim), shape=(act_dim,))
    torch.manual_seed(0)
    td3 = TD3(make_actor(obs_dim, spec), make_critic(obs_dim, act_dim), spec, **FAST_TD3)
    batch = transitions(batch_size, obs_dim, act_dim, torch.Generator().manual_seed(0))
    assert td3.loss.refusal(batch) is None
    timed = _products(lambda: (critic_products(), critic_products(), actor_products()))
    update = _products(lambda: (td3.update(batch), td3.update(batch)))
    assert type(td3.loss.value_loss(batch)[0].grad_fn).__name__ == "_CriticLossBackward"  # the fast loss ran
    assert update == timed and {name for name, _ in timed} == PRODUCTS


def test_the_es_chunk_is_the_backends_first_and_its_bounds_are_shares():
    es = bounds.es_bounds("HalfCheetah-v5", steps=2, repeats=1)
    parameters = 17 * 256 + 256 + 256 * 256 + 256 + 256 * 6 + 6  # the paper's actor on HalfCheetah
    assert es["pairs"] == 15 and es["offset_bytes"] == 15 * parameters * 4  # 120 members in 4 chunks on 2 cores
    assert 0 < es["most_share_of_raw"] < es["most_share_of_raw_reading_offsets"] < 1
