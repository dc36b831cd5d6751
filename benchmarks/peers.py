"""The cost of one TD3 learning frame here and in two peers, timed in one process in interleaved rounds.

A learning frame (Algorithm 1's TD3 step; Fujimoto et al. 2018): one env step with exploration noise
N(0, 0.1), its replay-buffer write and one TD3 update on a batch of 256, with the paper's networks
(actor 2x256 tanh, twin critics 2x256 ReLU) and values (Adam 3e-4, gamma 0.99, tau 0.005, target
smoothing 0.2 clipped at 0.5, policy delay 2), all read from conf/config.yaml. Methods, on each env:

  ours           the TD3 phase of the paper run as ``td3_phase`` plays it at the defaults
                 (``implementation=fast``): ``GymTD3Collector``, the ``noisy`` MultiBuffer write,
                 ``TD3.update`` on a batch drawn 0.5:0.2:0.3 from the three buffers, all three
                 ready (good and bad hold ``--prefill`` synthetic transitions, noisy the env's
                 frames; ``buffer.min_size`` = ``--prefill``), on ``td3.num_threads`` threads
  cleanrl_style  a plain single-file TD3 in the style of CleanRL's ``td3_continuous_action.py``
                 (:mod:`benchmarks.peer_cleanrl_td3`)
  torchrl_stock  TorchRL's stock pieces as its ``sota-implementations/td3`` example assembles them,
                 one frame per collected batch (:mod:`benchmarks.peer_torchrl_td3`)
  plain_update_<n>threads  the plain eager update alone, no env step (``benchmarks.td3_update.PlainTD3``
                 on a batch of ours' buffers, as ``benchmarks.bounds`` times it), on 1 thread and on
                 torch's default count

Each method is built and played in a process of its own (:class:`Process`; the plain updates' over
a buffer of ours built there), driven from here. Each implementation first fills its buffer with
``--prefill`` frames (the peers with uniform random actions, as their programs start; ours acting,
as the paper run does), untimed, and plays one untimed round. Then ``--repeats`` rounds, each
running ``--frames`` learning frames of every method in turn, so that the machine's drift falls on
all alike; every implementation runs on the job's cores (``torchrl_esrl.threads.job_cores``, what
``td3.num_threads=null`` gives ours). Per method: ms per frame (median of the rounds, and every
round), ``speedup_vs_<method>`` = that method's time / ours, ``best_peer`` and ours against it;
each implementation's TD3 values and network sizes as built, its last critic loss and whether its
actor and critic parameters moved in the rounds; the load average at start and end. The record
names the processor (``machine.cpu``).

Usage: ``python -m benchmarks.peers [--envs Walker2d-v5 HalfCheetah-v5] [--frames N] [--repeats R]
[--prefill P] [--capacity C] [--quick] [--out PATH]``. Hold running recipes first
(``scripts/pause_runs.sh pause``): the record states the load it saw.
"""
from __future__ import annotations

import argparse
import multiprocessing
import os

from benchmarks.common import fill, interleaved, on_threads, save_report  # sets OMP_WAIT_POLICY, first

import gymnasium as gym
import torch
from omegaconf import OmegaConf

from benchmarks.iteration import ROOT, paper_config
from benchmarks.peer_cleanrl_td3 import Args, CleanRLStyleTD3
from benchmarks.peer_torchrl_td3 import Config, TorchRLStockTD3
from benchmarks.td3_update import PlainTD3
from torchrl_esrl.algorithm.td3_phase import td3_phase
from torchrl_esrl.collectors.td3_collector import make_frame_batches
from torchrl_esrl.data.multibuffer import make_multibuffer
from torchrl_esrl.envs import make_train_env, quiet_logs
from torchrl_esrl.modules.networks import ACTIVATIONS, make_actor_critic
from torchrl_esrl.objectives.td3 import make_td3
from torchrl_esrl.run.determinism import seed_everything
from torchrl_esrl.threads import job_cores

PEERS = ("cleanrl_style", "torchrl_stock")


def env_groups() -> dict[str, str]:
    """Task id -> its ``env`` config group (conf/env/*.yaml)."""
    return {OmegaConf.load(path).id: path.stem for path in sorted((ROOT / "conf" / "env").glob("*.yaml"))}


def torch_loss_values(loss, target_update) -> dict:
    """The TD3 values a TorchRL ``TD3Loss`` and its ``SoftUpdate`` hold."""
    return {"gamma": float(loss.value_estimator.gamma), "tau": 1 - target_update.eps, "policy_noise": float(loss.policy_noise), "noise_clip": float(loss.noise_clip)}


def learning_rates(actor_optimizer, critic_optimizer) -> dict:
    return {"actor_lr": actor_optimizer.param_groups[0]["lr"], "critic_lr": critic_optimizer.param_groups[0]["lr"]}


def exploration_std(noise) -> float:
    """The standard deviation of an ``AdditiveGaussianModule``'s draws (sigma x std)."""
    return float(noise.sigma * noise.std)


def _vector(parameters) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in parameters])


class Ours:
    """The paper run's TD3 phase, built by the recipe's factories."""

    def __init__(self, cfg, prefill: int):
        seed_everything(cfg.seed)
        env = make_train_env(cfg)
        self.actor, critic = make_actor_critic(cfg, env)
        self.td3 = make_td3(cfg, self.actor, critic, env.action_spec)
        self.collector, self.batches = make_frame_batches(cfg, env, self.td3)
        self.buffer = make_multibuffer(cfg)
        self.updates_per_frame = cfg.td3.updates_per_frame
        self.obs_dim, self.act_dim = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
        for name in ("good", "bad"):  # what ES writes; their items' values do not change the cost
            fill(self.buffer, prefill, self.obs_dim, self.act_dim, name=name)
        self.frames(prefill)  # noisy reaches min_size: the buffers are ready
        assert self.buffer.ready()

    def frames(self, count: int) -> None:
        self.stats = td3_phase(count, self.batches, self.td3, self.buffer, updates_per_frame=self.updates_per_frame)

    def critic_loss(self) -> float:
        return float(self.stats["critic_loss"] or "nan")  # "": no update in the last call

    def hyperparameters(self) -> dict:
        td3 = self.td3
        return {**torch_loss_values(td3.loss, td3.target_update), **learning_rates(td3.actor_optimizer, td3.critic_optimizer),
                "policy_delay": td3.policy_delay, "exploration_noise": exploration_std(td3.exploration_policy[1]), "batch_size": self.buffer.batch_size}

    def parameters(self) -> dict[str, list]:
        return {"actor": list(self.actor.parameters()), "critics": list(self.td3.loss.qvalue_network_params.values(True, True))}

    def shutdown(self) -> None:
        self.collector.shutdown()


def networks(cfg) -> dict:
    """The paper's network sizes and activations, as the peers' settings name them."""
    return {"actor_hidden": tuple(cfg.actor.hidden), "critic_hidden": tuple(cfg.td3.critic_hidden),
            "actor_activation": ACTIVATIONS[cfg.actor.activation], "critic_activation": ACTIVATIONS[cfg.td3.critic_activation]}


class Peer:
    """A peer program driven through its training loop (``program.steps()``), ``prefill`` steps played."""

    def __init__(self, program, prefill: int):
        self.program, self.loop = program, program.steps()
        self.frames(prefill)

    def frames(self, count: int) -> None:
        loop = self.loop
        for _ in range(count):
            next(loop)


class CleanRLStyle(Peer):
    def __init__(self, cfg, prefill: int, capacity: int):
        c = cfg.td3
        program = CleanRLStyleTD3(Args(
            env_id=cfg.env.id, seed=cfg.seed, buffer_size=capacity, learning_rate=c.lr, gamma=c.gamma, tau=c.tau,
            batch_size=cfg.buffer.batch_size, policy_noise=c.policy_noise, exploration_noise=c.exploration_noise,
            learning_starts=prefill, policy_frequency=c.policy_delay, noise_clip=c.noise_clip, **networks(cfg),
        ))
        super().__init__(program, prefill + 1)  # it learns after global step learning_starts

    def critic_loss(self) -> float:
        return float("nan") if self.program.qf_loss is None else float(self.program.qf_loss)

    def hyperparameters(self) -> dict:
        p, a = self.program, self.program.args
        return {"gamma": a.gamma, "tau": a.tau, "policy_noise": a.policy_noise, "noise_clip": a.noise_clip,
                **learning_rates(p.actor_optimizer, p.q_optimizer), "policy_delay": a.policy_frequency,
                "exploration_noise": a.exploration_noise * float(p.actor.action_scale.unique()), "batch_size": a.batch_size}

    def parameters(self) -> dict[str, list]:
        p = self.program
        return {"actor": list(p.actor.parameters()), "critics": [*p.qf1.parameters(), *p.qf2.parameters()]}

    def shutdown(self) -> None:
        self.program.envs.close()


class TorchRLStock(Peer):
    def __init__(self, cfg, prefill: int, capacity: int):
        c = cfg.td3
        program = TorchRLStockTD3(Config(
            env_id=cfg.env.id, seed=cfg.seed, max_episode_steps=cfg.env.max_episode_steps or gym.spec(cfg.env.id).max_episode_steps, init_random_frames=prefill,
            frames_per_batch=c.frames_per_batch, buffer_size=capacity, batch_size=cfg.buffer.batch_size, prefetch=3,
            lr=c.lr, gamma=c.gamma, tau=c.tau, policy_noise=c.policy_noise, noise_clip=c.noise_clip, policy_update_delay=c.policy_delay,
            utd_ratio=c.updates_per_frame, exploration_noise=c.exploration_noise, **networks(cfg),
        ))
        super().__init__(program, prefill)  # it learns from the batch that brings it to init_random_frames

    def critic_loss(self) -> float:
        return float("nan") if self.program.q_loss is None else float(self.program.q_loss)

    def hyperparameters(self) -> dict:
        p = self.program
        return {**torch_loss_values(p.loss_module, p.target_net_updater), **learning_rates(p.optimizer_actor, p.optimizer_critic),
                "policy_delay": p.cfg.policy_update_delay, "exploration_noise": exploration_std(p.exploration_policy[1]), "batch_size": p.replay_buffer.batch_size}

    def parameters(self) -> dict[str, list]:
        loss = self.program.loss_module
        trained = lambda params: [p for p in params.flatten_keys().values() if p.requires_grad]  # noqa: E731 - not TanhModule's bounds
        return {"actor": trained(loss.actor_network_params), "critics": trained(loss.qvalue_network_params)}

    def shutdown(self) -> None:
        self.program.shutdown()


class PlainUpdates:
    """The plain eager update alone (``benchmarks.td3_update.PlainTD3``) on batches of ours' buffers,
    one update per frame, no env step."""

    def __init__(self, cfg, prefill: int):
        self.ours = Ours(cfg, prefill)
        torch.manual_seed(cfg.seed)
        self.plain = PlainTD3(self.ours.obs_dim, self.ours.act_dim)

    def frames(self, count: int) -> None:
        for _ in range(count):
            self.plain.update(self.ours.buffer.sample())

    def shutdown(self) -> None:
        self.ours.shutdown()


def build(method: str, env_id: str, prefill: int, capacity: int):
    """``(implementation, its torch threads)`` of a method's name (``ours``, a peer, ``plain_update_<n>thread[s]``)."""
    cfg = paper_config(env_groups()[env_id], capacity)
    cfg.buffer.min_size = prefill
    if method == "ours":
        ours = Ours(cfg, prefill)
        return ours, ours.td3.num_threads
    if method == "cleanrl_style":
        return CleanRLStyle(cfg, prefill, capacity), job_cores()
    if method == "torchrl_stock":
        return TorchRLStock(cfg, prefill, capacity), job_cores()
    return PlainUpdates(cfg, prefill), int(method.removeprefix("plain_update_").split("thread")[0])


def serve(method: str, env_id: str, prefill: int, capacity: int, connection) -> None:
    """A method's process: builds it, then plays the frame counts it receives, each on its threads,
    answering each when done; on ``None``, sends its report (:meth:`Process.finish`) and ends."""
    quiet_logs()
    implementation, threads = build(method, env_id, prefill, capacity)
    parts = getattr(implementation, "parameters", dict)
    before = {part: _vector(p) for part, p in parts().items()}
    connection.send(threads)
    while (count := connection.recv()) is not None:
        on_threads(threads, lambda: implementation.frames(count))()
        connection.send(None)
    report = {}
    if before:  # an implementation, not the plain update
        report = {"critic_loss": implementation.critic_loss(), "hyperparameters": implementation.hyperparameters(),
                  "parameters_moved": {part: not torch.equal(before[part], _vector(p)) for part, p in parts().items()},
                  "parameter_count": {part: sum(x.numel() for x in p) for part, p in parts().items()}}
    implementation.shutdown()
    connection.send(report)


class Process:
    """A method built and played in a process of its own (spawned), driven by :func:`interleaved` from here.

    One process would let each implementation's threads slow the others': a process whose threads
    other than the main one have run torch's OpenMP regions (TorchRL's prefetching buffer samples
    on three) holds more OpenMP threads than cores, and libgomp then makes every thread of every
    later parallel region sleep between regions instead of spinning, which multiplied a 2-thread
    update's time by about 3 on one processor (docs/performance_peers.md).
    """

    def __init__(self, method: str, env_id: str, prefill: int, capacity: int):
        context = multiprocessing.get_context("spawn")
        self.connection, child = context.Pipe()
        self.process = context.Process(target=serve, args=(method, env_id, prefill, capacity, child), daemon=True)
        self.process.start()
        self.threads = self.connection.recv()

    def frames(self, count: int) -> None:
        self.connection.send(count)
        self.connection.recv()

    def finish(self) -> dict:
        """The implementation's critic loss, TD3 values, parameter counts and whether they moved ({} for a plain update)."""
        self.connection.send(None)
        report = self.connection.recv()
        self.process.join()
        return report


def measure(env_id: str, frames: int, repeats: int, prefill: int, capacity: int) -> dict:
    names = ["ours", *PEERS, *(f"plain_update_{count}thread{'s' if count > 1 else ''}" for count in sorted({1, job_cores()}))]
    processes = {name: Process(name, env_id, prefill, capacity) for name in names}
    methods = {name: lambda process=process: process.frames(frames) for name, process in processes.items()}
    timings = {
        name: {"ms_per_frame": t["s_per_call"] / frames * 1e3, "best_ms_per_frame": t["best_s_per_call"] / frames * 1e3,
               "rounds_ms_per_frame": [seconds / frames * 1e3 for seconds in t["rounds_s_per_call"]], "torch_threads": processes[name].threads}
        for name, t in interleaved(methods, calls=1, repeats=repeats, warmup=1).items()  # one call: `frames` frames
    }
    finished = {name: process.finish() for name, process in processes.items()}
    implementations = {name: finished[name] for name in ("ours", *PEERS)}
    ours_ms = timings["ours"]["ms_per_frame"]
    plain_names = [name for name in timings if name.startswith("plain_update")]
    best_peer = min(PEERS, key=lambda name: timings[name]["ms_per_frame"])
    best_plain = min(plain_names, key=lambda name: timings[name]["ms_per_frame"])
    return {
        "env": env_id, "frames_per_round": frames, "repeats": repeats, "prefill": prefill, "capacity": capacity, "batch_size": paper_config().buffer.batch_size,
        "processes": "one per method",
        "methods": timings,
        **{f"speedup_vs_{name}": timings[name]["ms_per_frame"] / ours_ms for name in timings if name != "ours"},
        "best_peer": best_peer, "speedup_vs_best_peer": timings[best_peer]["ms_per_frame"] / ours_ms,
        "best_plain_update": best_plain, "speedup_vs_best_plain_update": timings[best_plain]["ms_per_frame"] / ours_ms,
        **{key: {name: report[key] for name, report in implementations.items()} for key in ("critic_loss", "parameters_moved", "hyperparameters", "parameter_count")},
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=["Walker2d-v5", "HalfCheetah-v5"], choices=sorted(env_groups()), metavar="ENV")
    parser.add_argument("--frames", type=int, default=None, help="learning frames per method and round (default 1000; --quick 100)")
    parser.add_argument("--repeats", type=int, default=None, help="rounds (default 5; --quick 2)")
    parser.add_argument("--prefill", type=int, default=None, help="frames in each buffer before the rounds, at least the batch (default 5000; --quick 300)")
    parser.add_argument("--capacity", type=int, default=None, help="items per replay buffer (default 1,000,000; --quick 10,000)")
    parser.add_argument("--quick", action="store_true", help="small buffers, few frames and rounds: checks that it runs")
    parser.add_argument("--out", default="benchmarks/results/peers.json")
    args = parser.parse_args(argv)

    def chosen(value, quick, default):
        return value if value is not None else quick if args.quick else default

    frames, repeats = chosen(args.frames, 100, 1000), chosen(args.repeats, 2, 5)
    prefill, capacity = chosen(args.prefill, 300, 5000), chosen(args.capacity, 10_000, 1_000_000)
    batch_size = paper_config().buffer.batch_size
    for name, value, least in (("--frames", frames, 1), ("--repeats", repeats, 1), ("--prefill", prefill, batch_size), ("--capacity", capacity, prefill)):
        if value < least:
            parser.exit(2, f"{parser.prog}: error: {name} must be at least {least}, got {value}\n")
    quiet_logs()
    report = {"load_average_1min": {"start": os.getloadavg()[0]}, "envs": {}}
    for env_id in args.envs:
        report["envs"][env_id] = r = measure(env_id, frames, repeats, prefill, capacity)
        for name, t in r["methods"].items():
            ratio = "" if name == "ours" else f"  {r[f'speedup_vs_{name}']:.2f}x ours' time"
            print(f"{env_id} {name:22s} {t['ms_per_frame']:7.3f} ms/frame on {t['torch_threads']} thread(s){ratio}")
    report["load_average_1min"]["end"] = os.getloadavg()[0]
    save_report(report, args.out)
    print(f"load average (1 min) {report['load_average_1min']['start']:.2f} -> {report['load_average_1min']['end']:.2f}; record {args.out}")
    return report


if __name__ == "__main__":
    main()
