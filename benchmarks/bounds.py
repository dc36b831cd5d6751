"""What float32 arithmetic on this machine leaves to gain in the loop's two hot parts, timed beside them.

- **TD3 update.** The matrix products of one update alone, back to back on preallocated inputs: the
  calls :mod:`torchrl_esrl.objectives.mlp_chain_rule` makes for one critic update and, every
  ``policy_delay`` = 2 updates, one actor update (the same shapes, transposes and ops: ``addmm``,
  ``baddbmm`` over the stacked twin critics, ``matmul``), at the paper's sizes. Interleaved with the
  plain PyTorch update (:class:`benchmarks.td3_update.PlainTD3`) and the loop's update (``TD3`` with
  ``make_td3``'s fast pieces) in float32 and with ``precision="bf16"``, each at 1 and 2 threads; the
  products are also timed in bfloat16. An update that computes these products in
  float32 with these kernels takes at least their time: ``plain / products`` is the most any such
  update can gain over the plain one. Their FLOPs and the plain update's (``torch.utils.flop_counter``)
  give their rates.
- **ES evaluation.** Per env step of one chunk as ``MujocoBatchBackend`` plays it on one core (15
  mirrored pairs, the default chunking of 120 members on 2 cores): the chunk's raw ``mujoco.batch``
  physics (fixed controls) and its mirrored forward (:meth:`PopulationActor.mirrored`, one BLAS
  thread), each alone, and a read of the bytes of the pairs' offsets (a BLAS matrix-vector product over each array), which every float32
  forward of the population reads at every step. ``physics / (physics + forward)`` is the highest
  share of raw speed an evaluation reaches that runs both on the same core; both timed alone, with
  the cache to themselves, it is an upper bound (inside a rollout each evicts the other).

Usage: ``python -m benchmarks.bounds [--envs HalfCheetah-v5 ...] [--repeats 5] [--out PATH]``. Hold
running recipes first (``scripts/pause_runs.sh pause``): the record states the load it saw.
"""
from __future__ import annotations

import argparse
import time

from benchmarks.common import SHAPES, fill, interleaved, on_threads, save_report  # sets OMP_WAIT_POLICY, first

import gymnasium as gym
import mujoco
import mujoco.batch
import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode
from torchrl.data import Bounded

from benchmarks.es_population import make_population
from benchmarks.td3_update import FAST_TD3, PlainTD3
from torchrl_esrl.collectors.mujoco_batch import MujocoBatchBackend
from torchrl_esrl.data.multibuffer import MultiBuffer
from torchrl_esrl.modules.networks import make_actor, make_critic
from torchrl_esrl.modules.population import PopulationActor, one_blas_thread
from torchrl_esrl.objectives import mlp_chain_rule as chain
from torchrl_esrl.objectives.td3 import TD3
from torchrl_esrl.threads import torch_threads

BATCH, HIDDEN, POLICY_DELAY = 256, 256, 2


def update_products(obs_dim: int, act_dim: int, batch: int = BATCH, hidden: int = HIDDEN, dtype=torch.float32):
    """``(critic_products, actor_products)``: callables making the matrix products of one critic
    update and of one actor update through :mod:`~torchrl_esrl.objectives.mlp_chain_rule` itself, on
    layers without activations and asking for the weights' gradients only, in ``dtype``."""
    g = torch.Generator().manual_seed(0)

    def randn(*shape):
        return torch.randn(*shape, generator=g).to(dtype)

    sizes = {"actor": [(obs_dim, hidden), (hidden, hidden), (hidden, act_dim)],
             "critic": [(obs_dim + act_dim, hidden), (hidden, hidden), (hidden, 1)]}

    def network(stack, kind):  # (weight, bias, no activation) layers: the products alone
        return [(randn(*stack, out, inp), randn(*stack, out), None) for inp, out in sizes[kind]]

    actor, target_actor = network((), "actor"), network((), "actor")
    critics, target_critics = network((2,), "critic"), network((2,), "critic")
    critic1 = [(w[0], b[0], None) for w, b, _ in critics]
    observation, critic_input = randn(batch, obs_dim), randn(batch, obs_dim + act_dim)
    weights_only, no_parameters = (True, False) * 3, (False,) * 6

    def critic_products():
        chain.forward(target_actor, observation)
        stacked_input = critic_input.expand(2, *critic_input.shape)
        chain.forward(target_critics, stacked_input)
        inputs = []
        q = chain.forward(critics, stacked_input, inputs)
        chain.backward(critics, inputs, q, weights_only)

    def actor_products():
        actor_inputs, critic_inputs = [], []
        chain.forward(actor, observation, actor_inputs)
        value = chain.forward(critic1, critic_input, critic_inputs)
        _, grad = chain.backward(critic1, critic_inputs, value, no_parameters, input_grad=True)
        chain.backward(actor, actor_inputs, grad[:, obs_dim:].contiguous(), weights_only)

    return critic_products, actor_products


def flops_per_update(update) -> float:
    """FLOPs of ``update()`` (torch's flop counter), averaged over ``policy_delay`` calls."""
    with FlopCounterMode(display=False) as counter:
        for _ in range(POLICY_DELAY):
            update()
    return counter.get_total_flops() / POLICY_DELAY


def td3_bounds(env_id: str, repeats: int, calls: int, capacity: int) -> dict:
    obs_dim, act_dim = SHAPES[env_id]
    buffer = MultiBuffer(ratio=(0.5, 0.2, 0.3), capacity=capacity, batch_size=BATCH, direct_reads=True)
    for name in buffer.names:
        fill(buffer, capacity, obs_dim, act_dim, name=name)
    spec = Bounded(-torch.ones(act_dim), torch.ones(act_dim), shape=(act_dim,))
    torch.manual_seed(0)
    plain = PlainTD3(obs_dim, act_dim)
    fast = TD3(make_actor(obs_dim, spec), make_critic(obs_dim, act_dim), spec, **FAST_TD3)
    fast_bf16 = TD3(make_actor(obs_dim, spec), make_critic(obs_dim, act_dim), spec, precision="bf16", **FAST_TD3)

    def products_in(dtype):
        critic_products, actor_products = update_products(obs_dim, act_dim, dtype=dtype)
        calls = [0]

        def products():
            critic_products()
            calls[0] += 1
            if calls[0] % POLICY_DELAY == 0:
                actor_products()
        return products

    products, products_bf16 = products_in(torch.float32), products_in(torch.bfloat16)

    methods = {}
    for threads in (1, 2):
        methods[f"plain_{threads}threads"] = on_threads(threads, lambda: plain.update(buffer.sample()))
        methods[f"loop_{threads}threads"] = on_threads(threads, lambda: fast.update(buffer.sample()))
        methods[f"products_{threads}threads"] = on_threads(threads, products)
        methods[f"loop_bf16_{threads}threads"] = on_threads(threads, lambda: fast_bf16.update(buffer.sample()))
        methods[f"products_bf16_{threads}threads"] = on_threads(threads, products_bf16)
    timings = interleaved(methods, calls=calls, repeats=repeats, warmup=10)
    torch.manual_seed(0)
    plain_flops = flops_per_update(lambda td3=PlainTD3(obs_dim, act_dim), batch=buffer.sample(): td3.update(batch))
    products_flops = flops_per_update(products_in(torch.float32))
    best = {kind: min(timings[f"{kind}_{n}threads"]["s_per_call"] for n in (1, 2)) for kind in ("plain", "loop", "products", "loop_bf16", "products_bf16")}
    return {
        "env": env_id, "capacity": capacity, "batch_size": BATCH, "methods": timings,
        "plain_update_mflop": plain_flops / 1e6,
        "products_mflop": products_flops / 1e6,  # the fast update's: it skips the first critic's weight gradients in the actor update
        "products_gflop_per_s": {n: products_flops / timings[f"products_{n}threads"]["s_per_call"] / 1e9 for n in (1, 2)},
        "best_ms": {kind: seconds * 1e3 for kind, seconds in best.items()},
        "loop_over_plain": best["plain"] / best["loop"],  # > 1: the loop's update is faster
        "most_over_plain": best["plain"] / best["products"],  # the products alone against plain
        "loop_bf16_over_loop": best["loop"] / best["loop_bf16"],  # > 1: td3.precision=bf16 is faster
        "products_bf16_over_products": best["products"] / best["products_bf16"],
    }


def es_bounds(env_id: str, steps: int, repeats: int, members: int = 120, cores: int = 2) -> dict:
    actor, _, mirrored = make_population(env_id, members)
    policy = PopulationActor(actor)
    chunk = MujocoBatchBackend(env_id, policy, nthread=cores).chunks(members, mirrored)[0]  # its default chunking
    pairs = chunk.pairs.stop - chunk.pairs.start
    center, offsets = policy.split_pairs(mirrored, chunk.pairs)
    env = gym.make(env_id).unwrapped
    batch = mujoco.batch.Batch(env.model, 2 * pairs, 1)
    row = np.empty(batch.nstate)
    for member in range(2 * pairs):
        env.reset(seed=1000 + member)
        mujoco.mj_getState(env.model, env.data, row, mujoco.mjtState.mjSTATE_INTEGRATION)
        batch.state[member] = row
    batch.bind("ctrl")[:] = np.random.default_rng(0).uniform(-0.5, 0.5, (2 * pairs, env.model.nu))
    observations = np.random.default_rng(1).standard_normal((2, pairs, env.observation_space.shape[0])).astype(np.float32)
    offset_arrays = [array for layer in offsets for array in layer]
    offset_bytes = sum(array.nbytes for array in offset_arrays)

    def physics():
        for _ in range(steps):
            batch.step(nstep=env.frame_skip)

    def forward():
        with one_blas_thread():
            for _ in range(steps):
                policy.mirrored(center, offsets, observations)

    rows = [(array.reshape(-1, array.shape[-1]), np.ones(array.shape[-1], dtype=array.dtype)) for array in offset_arrays]

    def read_offsets():  # one BLAS matrix-vector product per array: each byte read once, as a forward must
        with one_blas_thread():
            for _ in range(steps):
                for matrix, ones in rows:
                    matrix @ ones

    rounds = {name: [] for name in ("physics", "forward", "read_offsets")}
    with torch_threads(1):
        for _ in range(repeats):
            for name, fn in (("physics", physics), ("forward", forward), ("read_offsets", read_offsets)):
                start = time.perf_counter()
                fn()
                rounds[name].append((time.perf_counter() - start) / steps)
    per_step = {name: float(np.median(values)) for name, values in rounds.items()}
    return {
        "env": env_id, "pairs": pairs, "steps": steps, "frame_skip": env.frame_skip,
        "per_step_s": per_step, "rounds_per_step_s": rounds,
        "offset_bytes": offset_bytes, "offset_read_gb_per_s": offset_bytes / per_step["read_offsets"] / 1e9,
        "most_share_of_raw": per_step["physics"] / (per_step["physics"] + per_step["forward"]),
        "most_share_of_raw_reading_offsets": per_step["physics"] / (per_step["physics"] + per_step["read_offsets"]),
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=["HalfCheetah-v5", "Walker2d-v5"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--calls", type=int, default=50, help="TD3 updates per method and round")
    parser.add_argument("--steps", type=int, default=200, help="env steps per ES round")
    parser.add_argument("--capacity", type=int, default=1_000_000, help="items per buffer")
    parser.add_argument("--out", default="benchmarks/results/bounds.json")
    args = parser.parse_args(argv)
    report = {"td3": {}, "es": {}}
    for env_id in args.envs:
        report["td3"][env_id] = td3 = td3_bounds(env_id, args.repeats, args.calls, args.capacity)
        print(f"{env_id} TD3 update (best thread count): plain {td3['best_ms']['plain']:.2f} ms, loop {td3['best_ms']['loop']:.2f} ms "
              f"({td3['loop_over_plain']:.2f}x plain), its matrix products alone {td3['best_ms']['products']:.2f} ms "
              f"(at most {td3['most_over_plain']:.2f}x plain; {td3['products_mflop']:.0f} MFLOP, plain {td3['plain_update_mflop']:.0f}); bf16: loop {td3['best_ms']['loop_bf16']:.2f} ms "
              f"({td3['loop_bf16_over_loop']:.2f}x the float32 loop), products {td3['best_ms']['products_bf16']:.2f} ms")
        report["es"][env_id] = es = es_bounds(env_id, args.steps, args.repeats)
        ms = {name: seconds * 1e3 for name, seconds in es["per_step_s"].items()}
        print(f"{env_id} ES chunk of {es['pairs']} pairs, per step on one core: physics {ms['physics']:.3f} ms, forward {ms['forward']:.3f} ms, "
              f"offsets read {ms['read_offsets']:.3f} ms ({es['offset_read_gb_per_s']:.1f} GB/s): at most {es['most_share_of_raw']:.2f}x raw "
              f"(reading the offsets alone: {es['most_share_of_raw_reading_offsets']:.2f}x)")
    save_report(report, args.out)
    return report


if __name__ == "__main__":
    main()
