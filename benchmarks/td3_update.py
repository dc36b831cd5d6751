"""TD3 update rate: TorchRL TD3 (torchrl_esrl.objectives.td3.TD3) vs a hand-written plain PyTorch TD3 (figure 2).

Batch 256 from a MultiBuffer (0.5:0.2:0.3, three full HalfCheetah-shaped buffers), the paper's
networks (actor 17-256-256-6 tanh, twin critics 23-256-256-1 relu), Adam 3e-4, gamma 0.99,
tau 0.005, target smoothing 0.2 clipped at 0.5, policy delay 2. Sampling is included in every
method. Methods, interleaved in one run:

  plain         Fujimoto-style TD3 in plain PyTorch (nn.Sequential, separate target copies,
                default Adam, per-parameter soft update), 1 torch thread: the baseline
  plain_2threads  the same on 2 threads
  plain_fused   the same with fused Adam (reference: what the baseline gets from the same trick)
  torchrl_stock TD3() (the reference): TorchRL TD3Loss + SoftUpdate + default Adam
  torchrl_fast  TD3 with make_td3's fast pieces: ManualGradTD3Loss (stacked twin critics, Q1-only
                actor loss, hand-written gradients beneath loss.backward()) + ForeachSoftUpdate + fused Adam, 1 thread
  torchrl_fast_2threads  the same on 2 threads (the TD3 phase's ``td3.num_threads`` default on 2 cores, as the
                recipes run it)
  torchrl_fast_engine_2threads  the same with ``loss.backward()`` run by the autograd engine, as with an extra
                loss term or a gradient hook (``TD3.backward`` otherwise calls the hand-written backward itself)

Each method sets its thread count before every call. The process runs under libgomp's own
(spinning) wait policy, as the recipes do; ``--omp-passive`` runs it under
``OMP_WAIT_POLICY=PASSIVE``: the wait policy is read once, when torch loads, so the two are
separate processes.

Goal: the better torchrl_fast thread count >= 1.2x the better plain one.
Usage: ``python -m benchmarks.td3_update [--quick] [--omp-passive] [--out PATH]``.
"""
from __future__ import annotations

import argparse
import copy
import os
import sys

if "--omp-passive" in sys.argv:  # before torch loads
    os.environ["BENCHMARKS_OMP_PASSIVE"] = "1"

from benchmarks.common import SHAPES, fill, interleaved, on_threads, save_report  # sets OMP_WAIT_POLICY, first

import torch
import torch.nn.functional as F
from torch import nn
from torchrl.data import Bounded

from torchrl_esrl.data.multibuffer import MultiBuffer
from torchrl_esrl.modules.networks import make_actor, make_critic
from torchrl_esrl.objectives.td3 import TD3, ForeachSoftUpdate, ManualGradTD3Loss

FAST_TD3 = {"loss_class": ManualGradTD3Loss, "target_update_class": ForeachSoftUpdate, "optimizer_impl": "fused"}  # make_td3's fast pieces


def _mlp(inputs: int, outputs: int, activation, squash: bool = False) -> nn.Sequential:
    layers = [nn.Linear(inputs, 256), activation(), nn.Linear(256, 256), activation(), nn.Linear(256, outputs)]
    return nn.Sequential(*layers, *([nn.Tanh()] if squash else []))


class PlainTD3:
    """TD3 (Fujimoto et al. 2018) in plain PyTorch, action bounds [-1, 1] as HalfCheetah's."""

    def __init__(self, obs_dim: int, act_dim: int, lr=3e-4, gamma=0.99, tau=0.005, policy_noise=0.2, noise_clip=0.5, policy_delay=2, fused=False):
        self.actor = _mlp(obs_dim, act_dim, nn.Tanh, squash=True)
        self.q1, self.q2 = _mlp(obs_dim + act_dim, 1, nn.ReLU), _mlp(obs_dim + act_dim, 1, nn.ReLU)
        self.actor_t, self.q1_t, self.q2_t = (copy.deepcopy(m).requires_grad_(False) for m in (self.actor, self.q1, self.q2))
        options = {"fused": True} if fused else {}
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=lr, **options)
        self.critic_opt = torch.optim.Adam([*self.q1.parameters(), *self.q2.parameters()], lr=lr, **options)
        self.gamma, self.tau, self.noise, self.clip, self.delay, self.updates = gamma, tau, policy_noise, noise_clip, policy_delay, 0

    def update(self, batch) -> None:
        s, a, r = batch["observation"], batch["action"], batch["next", "reward"]
        s2, not_done = batch["next", "observation"], 1 - batch["next", "terminated"].float()
        with torch.no_grad():
            noise = (torch.randn_like(a) * self.noise).clamp(-self.clip, self.clip)
            a2 = (self.actor_t(s2) + noise).clamp(-1, 1)
            sa2 = torch.cat([s2, a2], -1)
            target = r + self.gamma * not_done * torch.min(self.q1_t(sa2), self.q2_t(sa2))
        sa = torch.cat([s, a], -1)
        critic_loss = F.mse_loss(self.q1(sa), target) + F.mse_loss(self.q2(sa), target)
        self.critic_opt.zero_grad()
        critic_loss.backward()
        self.critic_opt.step()
        self.updates += 1
        if self.updates % self.delay == 0:
            actor_loss = -self.q1(torch.cat([s, self.actor(s)], -1)).mean()
            self.actor_opt.zero_grad()
            actor_loss.backward()
            self.actor_opt.step()
            with torch.no_grad():
                for net, target_net in ((self.actor, self.actor_t), (self.q1, self.q1_t), (self.q2, self.q2_t)):
                    for p, tp in zip(net.parameters(), target_net.parameters()):
                        tp.data.copy_(self.tau * p.data + (1 - self.tau) * tp.data)


def run(capacity: int = 1_000_000, repeats: int = 7, calls: int = 50, env_id: str = "HalfCheetah-v5") -> dict:
    obs_dim, act_dim = SHAPES[env_id]
    buffer = MultiBuffer(ratio=(0.5, 0.2, 0.3), capacity=capacity, batch_size=256, direct_reads=True)  # as make_multibuffer's fast pieces
    for name in buffer.names:
        fill(buffer, capacity, obs_dim, act_dim, name=name)
    spec = Bounded(-torch.ones(act_dim), torch.ones(act_dim), shape=(act_dim,))

    def torchrl(td3_class=TD3, **kwargs):
        torch.manual_seed(0)
        td3 = td3_class(make_actor(obs_dim, spec), make_critic(obs_dim, act_dim), spec, **kwargs)
        return lambda: td3.update(buffer.sample())

    def plain(**kwargs):
        torch.manual_seed(0)
        td3 = PlainTD3(obs_dim, act_dim, **kwargs)
        return lambda: td3.update(buffer.sample())

    class EngineTD3(TD3):
        def backward(self, loss, optimizer):
            loss.backward()

    methods = {
        "plain": on_threads(1, plain()),
        "plain_2threads": on_threads(2, plain()),
        "plain_fused": on_threads(1, plain(fused=True)),
        "torchrl_stock": on_threads(1, torchrl()),
        "torchrl_fast": on_threads(1, torchrl(**FAST_TD3)),
        "torchrl_fast_2threads": on_threads(2, torchrl(**FAST_TD3)),
        "torchrl_fast_engine_2threads": on_threads(2, torchrl(EngineTD3, **FAST_TD3)),
    }
    timings = interleaved(methods, calls=calls, repeats=repeats, warmup=10)
    base = timings["plain"]["s_per_call"]
    for t in timings.values():
        t["updates_per_s"] = 1 / t["s_per_call"]
        t["ratio"] = base / t["s_per_call"]  # speed relative to plain: > 1 is faster
        t["ratio_best"] = timings["plain"]["best_s_per_call"] / t["best_s_per_call"]  # quietest rounds
    best_plain = min(timings["plain"]["s_per_call"], timings["plain_2threads"]["s_per_call"])
    best_fast = min(timings["torchrl_fast"]["s_per_call"], timings["torchrl_fast_2threads"]["s_per_call"])
    return {"env": env_id, "capacity": capacity, "batch_size": 256, "goal": "best torchrl_fast >= 1.2x the best plain (update rate)",
            "ratio_vs_best_plain": best_plain / best_fast,
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "libgomp default"),
            "met": best_plain / best_fast >= 1.2, "methods": timings}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="100k-item buffers, fewer repetitions")
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--calls", type=int, default=None)
    parser.add_argument("--omp-passive", action="store_true", help="OMP_WAIT_POLICY=PASSIVE instead of libgomp's default (read at import)")
    parser.add_argument("--out", default="benchmarks/results/td3_update.json")
    args = parser.parse_args(argv)
    report = run(100_000 if args.quick else 1_000_000, repeats=args.repeats or (3 if args.quick else 9), calls=args.calls or (20 if args.quick else 50))
    for name, t in report["methods"].items():
        print(f"{name:22s} {t['updates_per_s']:8.1f} updates/s  {t['ratio']:5.2f}x plain (best rounds {t['ratio_best']:5.2f}x)")
    print(f"best torchrl_fast / best plain: {report['ratio_vs_best_plain']:.2f}x (goal >= 1.2x: {'met' if report['met'] else 'not met'})")
    save_report(report, args.out)
    return report


if __name__ == "__main__":
    main()
