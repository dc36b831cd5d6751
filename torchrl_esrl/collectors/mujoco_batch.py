"""Fast ES population evaluation on MuJoCo's batched executor (paper, Algorithm 1 "Evaluate").

:class:`MujocoBatchBackend` plays one episode per population member like the reference
``"gym"`` backend (:class:`torchrl_esrl.collectors.gym_backend.GymBackend`), but steps a chunk of
members' physics with one ``mujoco.batch.Batch.step`` call per env step (for Ant on a batch of one
thread, all substeps but the last, which the worker plays member by member on its own ``MjData``
to read gymnasium's contact forces from it) and recomputes
observations, rewards, termination and truncation of the gymnasium v5 tasks in vectorised numpy
over the chunk's live members. Members never interact, so each worker thread plays whole chunks
on a batch of its own: the workers do not wait for each other within an episode.

Why hand-written: gymnasium computes observations and rewards one env at a time from an
``MjData``; ``mujoco.batch`` gives the raw state of all simulations as one array but knows nothing
about the tasks. The formulas here and in :mod:`~torchrl_esrl.collectors.mujoco_tasks` (the tasks' rules)
are those of ``gymnasium/envs/mujoco/*_v5.py``; every setting
they read (reward weights, healthy ranges, ``frame_skip``, Ant's main body, the observation
layout) is read from the gymnasium env the backend builds from the run's
:class:`~torchrl_esrl.envs.EnvSpec`, so it cannot drift from gymnasium's. Keyword arguments
outside :data:`~torchrl_esrl.collectors.mujoco_tasks.REPRODUCED_KWARGS` and
:data:`~torchrl_esrl.collectors.mujoco_tasks.RENDERING_KWARGS` are refused by
:meth:`MujocoBatchBackend.refusal`, naming them; the tests check observations, actions, rewards
and flags against gymnasium, per keyword.

Initial states are gymnasium's own: one gymnasium env of the task is reset with each member's
seed and its whole integration state (``mj_getState(mjSTATE_INTEGRATION)``: time, qpos, qvel,
warm start, controls, ...) is copied into that member's row of the batch. This reproduces
``reset(seed=s)`` exactly without re-implementing each task's reset noise.
"""
from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import mujoco
import mujoco.batch
import numpy as np
import torch

from torchrl_esrl.collectors.generation import Generation, transitions_from_arrays
from torchrl_esrl.envs import EnvSpec, as_env_spec
from torchrl_esrl.collectors.mujoco_tasks import (
    RENDERING_KWARGS, REPRODUCED_KWARGS, TASKS, TaskRules, env_refusals, observation_layout, spec_refusals,
)
from torchrl_esrl.modules.population import Mirrored, PopulationActor, one_blas_thread
from torchrl_esrl.threads import process_cores
from torchrl_esrl.torchrl_private import gym_mujoco_constants

__all__ = ["MujocoBatchBackend", "RENDERING_KWARGS", "REPRODUCED_KWARGS", "TASKS", "TaskRules"]  # the tasks' rules live in mujoco_tasks

_INTEGRATION_STATE = mujoco.mjtState.mjSTATE_INTEGRATION


@dataclass(frozen=True)
class _Chunk:
    """Population members one worker plays together, on one batch."""

    members: np.ndarray  # their rows in the population
    pairs: slice | None  # with mirrored pairs: the chunk's pairs (members = pairs and K + pairs)


def _runs(pairs_live: np.ndarray, pairs: int) -> list[tuple[int, int]]:
    """The runs ``(start, stop)`` of contiguous pairs among ``pairs`` that hold a member of ``pairs_live``."""
    alive = np.zeros(pairs + 2, dtype=np.int8)
    alive[pairs_live + 1] = 1
    edges = np.flatnonzero(np.diff(alive))
    return list(zip(edges[0::2].tolist(), edges[1::2].tolist()))


def _policy_refusal(population_actor, observation_dim: int) -> str | None:
    """:meth:`MujocoBatchBackend.policy_refusal` with the observation size known."""
    probe = getattr(population_actor, "nondeterminism", None)
    if isinstance(population_actor, PopulationActor) or probe is None:
        return None
    reason = probe(observation_dim)
    return None if reason is None else f"{reason}, and the worker threads play members in an order that differs from run to run"


class _Worker:
    """One thread's own MuJoCo state (gymnasium envs and ``MjData`` are not thread-safe): the env
    whose ``reset(seed)`` gives each member gymnasium's initial state, a batch per chunk size, and
    Ant's scratch data."""

    def __init__(self, spec: EnvSpec, contact_forces: bool):
        self.reset_env = spec.make_gym()
        self.model = self.reset_env.unwrapped.model
        self.batches: dict[int, mujoco.batch.Batch] = {}
        self.scratch = mujoco.MjData(self.model) if contact_forces else None

    def batch(self, members: int, nthread: int, persistent: bool) -> mujoco.batch.Batch:
        if members not in self.batches:
            self.batches[members] = mujoco.batch.Batch(self.model, members, min(nthread, members), persistent)
        return self.batches[members]


class MujocoBatchBackend:
    """ES backend: chunks of the population on ``mujoco.batch`` batches, one batched policy forward
    per chunk and step.

    Args:
        env: an :class:`~torchrl_esrl.envs.EnvSpec` (or a gymnasium id, or its short name) that
            :meth:`refusal` takes: a task of :data:`TASKS` as gymnasium defines it.
        population_actor: evaluates members' actors from their flat parameters.
        max_episode_steps: time limit (the env spec's when None).
        nthread: threads in all (default: the cores this process may run on, ``threads.process_cores``).
        workers: threads that each play whole chunks on a batch of their own, taking the next
            chunk when done with one (default: 2, or 1 on one thread); each batch steps on
            ``nthread // workers`` MuJoCo threads. More workers make smaller chunks, and every chunk
            pays its numpy bookkeeping per step under the GIL (not measured beyond 2 cores).
        chunks_per_worker: the population is cut into up to ``workers * chunks_per_worker``
            chunks of (nearly) equal size: more than one per worker evens out episodes that end
            early, and each chunk's noise is a smaller share of the cache.
        min_chunk: members a chunk holds at least, unless that would leave a worker idle: each
            chunk pays its own numpy bookkeeping per step under the GIL.
        persistent: keep one ``MjData`` per simulation (forced for Ant's contact forces when a batch
            steps on more than one thread).

    Every member's arithmetic is its own (its physics, and its forward: :class:`PopulationActor`
    computes each member, or each mirrored pair, with products of the same shapes), so every
    chunking and every number of workers give each member bit for bit the same episode
    (tests/test_mujoco_batch.py). Workers never wait for each other within an episode, and a
    chunk's share of the population's parameters stays in cache between its steps.

    Given the population as :class:`~torchrl_esrl.modules.population.Mirrored` pairs (OpenAI-ES),
    chunks are made of whole pairs and the forward is :meth:`PopulationActor.mirrored
    <torchrl_esrl.modules.population.PopulationActor.mirrored>`: each pair's noise is read once per
    step for both members. Its actions equal the flat rows' up to float32 rounding (the rollout
    stays deterministic); the ``gym`` reference computes the same forward when given the pairs.
    """

    name = "mujoco_batch"

    def __init__(
        self,
        env: "str | EnvSpec",
        population_actor: PopulationActor,
        max_episode_steps: int | None = None,
        nthread: int | None = None,
        workers: int | None = None,
        chunks_per_worker: int = 2,
        min_chunk: int = 16,
        persistent: bool = False,
    ):
        spec = as_env_spec(env, max_episode_steps)
        reasons = spec_refusals(spec)
        if reasons:
            raise ValueError(f"mujoco_batch backend cannot play this env exactly as gymnasium would: {', '.join(reasons)}")
        self.env_id = spec.id
        self.rules = TASKS[self.env_id]
        self.policy = population_actor
        self.nthread = int(nthread or process_cores())
        workers = int(workers or min(self.nthread, 2))
        self.workers = [_Worker(spec, self.rules.contact_forces) for _ in range(workers)]
        self.threads_per_batch = max(1, self.nthread // workers)
        # Ant's contact forces need the MjData each step leaves behind: on a batch of one thread the
        # worker plays each step's last substep on its own MjData; otherwise a persistent batch keeps
        # one per simulation, copied out member by member.
        self.last_substep_in_worker = self.rules.contact_forces and self.threads_per_batch == 1
        self.persistent = bool(persistent or (self.rules.contact_forces and not self.last_substep_in_worker))
        self.chunks_per_worker, self.min_chunk = int(chunks_per_worker), int(min_chunk)
        self._pool: ThreadPoolExecutor | None = None
        reset_env = self.workers[0].reset_env
        reasons = env_refusals(spec, reset_env)
        if reasons:
            raise ValueError(f"mujoco_batch backend cannot play this env exactly as gymnasium would: {', '.join(reasons)}")
        env = reset_env.unwrapped
        self.constants = gym_mujoco_constants(env)  # gymnasium's own values, so the batch cannot drift from them
        self.model = env.model
        self.skipped_qpos, self.contact_forces_in_obs, _ = observation_layout(self.rules, self.constants, self.model)
        # The body whose x gives Ant's progress, as gymnasium's data.body(main_body) resolves it.
        self.x_body = int(env.data.body(self.constants["_main_body"]).id) if self.rules.x_from_main_body else None
        self.frame_skip = int(env.frame_skip)
        self.dt = env.dt  # the same float gymnasium divides by
        self.horizon = int(spec.max_episode_steps or reset_env.spec.max_episode_steps or 1000)
        self.observation_dim = int(np.prod(reset_env.observation_space.shape))
        self.action_dim = int(self.model.nu)
        reason = _policy_refusal(population_actor, self.observation_dim)
        if reason is not None:
            raise ValueError(f"mujoco_batch backend cannot play this actor exactly as the gym backend would: {reason}")
        # gymnasium multiplies the float32 sum of squared actions: the product's dtype is float32
        # for a Python number, and the weight's for a numpy one.
        self.ctrl_cost_weight = np.float32(1) * self.constants["_ctrl_cost_weight"]

    @staticmethod
    def refusal(env) -> str | None:
        """Why this backend cannot play ``env`` (an id or an :class:`~torchrl_esrl.envs.EnvSpec`)
        exactly as the ``gym`` reference would, in a few words naming the field, or None: it
        recomputes observations and rewards from the raw MuJoCo state by the task's own rules, so
        it takes the tasks of :data:`TASKS`, the keyword arguments of :data:`REPRODUCED_KWARGS`
        and :data:`RENDERING_KWARGS` (decided on the gymnasium env they make), no wrapper and no
        transform."""
        try:
            spec = as_env_spec(env)
        except Exception:  # noqa: BLE001 - an id that does not resolve is not one of the tasks
            return f"env.id: {env!r} is not a task it knows ({', '.join(TASKS)})"
        reasons = spec_refusals(spec)
        if not reasons and spec.kwargs:
            try:
                gym_env = spec.make_gym()
            except Exception as error:  # noqa: BLE001 - gymnasium cannot make it: neither can this backend
                text = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
                return text if text.startswith("env.") else f"env.kwargs: {text}"
            try:
                reasons = env_refusals(spec, gym_env)
            finally:
                gym_env.close()
        return ", ".join(reasons) if reasons else None

    @staticmethod
    def policy_refusal(population_actor, env) -> str | None:
        """Why this backend cannot play the members of ``population_actor`` on ``env`` exactly as
        the ``gym`` reference would, or None. Its worker threads play chunks of members in an
        order that differs from run to run, so the members' forward must be a deterministic
        function of their parameters and observation: :class:`PopulationActor` is (arithmetic
        on the flat vectors); a population with a ``nondeterminism`` method is asked
        (:class:`~torchrl_esrl.modules.population.ModulePopulation`: a forward that draws random
        numbers or keeps state is not); any other is taken as it is."""
        if isinstance(population_actor, PopulationActor) or getattr(population_actor, "nondeterminism", None) is None:
            return None
        return _policy_refusal(population_actor, as_env_spec(env).sizes().observation_dim)

    def chunks(self, population: int, mirrored: Mirrored | None = None) -> list[_Chunk]:
        """The population cut into chunks of (nearly) equal size: of whole pairs with ``mirrored``,
        of contiguous rows otherwise."""
        workers = len(self.workers)
        count = min(workers * self.chunks_per_worker, max(workers, population // self.min_chunk))
        if mirrored is None:
            return [_Chunk(rows, None) for rows in np.array_split(np.arange(population), min(count, population))]
        pairs = mirrored.offsets.shape[0]
        return [
            _Chunk(np.concatenate([block, pairs + block]), slice(int(block[0]), int(block[-1]) + 1))
            for block in np.array_split(np.arange(pairs), min(count, pairs))
        ]

    def _in_workers(self, chunks: list[_Chunk], play: Callable[[_Worker, _Chunk], None]) -> None:
        """``play(worker, chunk)`` for every chunk, each worker taking the next chunk when done;
        the calling thread is the first worker."""
        workers = self.workers[: len(chunks)]
        pending, lock = iter(chunks), threading.Lock()

        def work(worker: _Worker) -> None:
            while True:
                with lock:
                    chunk = next(pending, None)
                if chunk is None:
                    return
                play(worker, chunk)

        if len(workers) > 1 and self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=len(self.workers) - 1, thread_name_prefix="mujoco-batch")
        others = [self._pool.submit(work, worker) for worker in workers[1:]]
        try:
            work(workers[0])
        finally:
            for other in others:
                other.result()

    @torch.no_grad()
    def rollout(self, params: torch.Tensor, seeds: Sequence[int], mirrored: Mirrored | None = None) -> Generation:
        """One episode per row of ``params``; with ``mirrored`` (the same population as pairs) the
        forward reads each pair's noise once."""
        population = params.shape[0]
        out = self._padded(population)

        def play(worker: _Worker, chunk: _Chunk) -> None:
            episodes = self._play(worker, params, [int(seeds[m]) for m in chunk.members], mirrored, chunk)
            for key, array in episodes.items():
                out[key][chunk.members] = array

        with one_blas_thread():  # numpy's BLAS for the forward: one thread per worker
            self._in_workers(self.chunks(population, mirrored), play)
        obs_traj, returns = out["obs_traj"], out["rewards"].sum(axis=1)
        transitions = transitions_from_arrays(
            obs_traj[:, :-1], out["actions"], obs_traj[:, 1:], out["rewards"], out["terminated"], out["truncated"], out["lengths"], returns
        )
        return Generation(torch.as_tensor(returns), torch.as_tensor(out["lengths"]), transitions)

    def _padded(self, members: int) -> dict[str, np.ndarray]:
        """Padded per-member outputs. One observation trajectory per member serves as both
        "observation" (steps 0..T-1) and "next/observation" (steps 1..T): no duplicate copies."""
        horizon = self.horizon
        return {
            "obs_traj": np.zeros((members, horizon + 1, self.observation_dim), dtype=np.float32),
            "actions": np.zeros((members, horizon, self.action_dim), dtype=np.float32),
            "rewards": np.zeros((members, horizon)),
            "terminated": np.zeros((members, horizon), dtype=bool),
            "truncated": np.zeros((members, horizon), dtype=bool),
            "lengths": np.zeros(members, dtype=np.int64),
        }

    def _policy(self, params: torch.Tensor, mirrored: Mirrored | None, chunk: _Chunk) -> Callable[[np.ndarray, np.ndarray | None], np.ndarray]:
        """The chunk's forward: its members' observations [n, obs] and its live members (None: all)
        -> the live members' actions [live, act]. Over mirrored pairs it computes only the pairs
        with a live member, on runs of contiguous pairs: views of their offsets, each pair's
        products of the same shapes, so bit for bit the actions of the forward over all the pairs."""
        if chunk.pairs is None:
            rows = params[int(chunk.members[0]) : int(chunk.members[-1]) + 1]  # contiguous: a view
            layers = self.policy.split(rows)

            def rows_forward(observations: np.ndarray, live: np.ndarray | None) -> np.ndarray:
                # every member: each member's actions are those of the reference's forward over all
                actions = self.policy(rows, torch.from_numpy(observations), layers).numpy()
                return actions if live is None else actions[live]

            return rows_forward
        center, offsets = self.policy.split_pairs(mirrored, chunk.pairs)
        pairs = chunk.pairs.stop - chunk.pairs.start
        runs: dict[int, list[tuple[int, int]]] = {}  # by the number of live members: the live set only shrinks

        def pairs_forward(observations: np.ndarray, live: np.ndarray | None) -> np.ndarray:
            observations = observations.reshape(2, pairs, -1)
            if live is None:
                return self.policy.mirrored(center, offsets, observations).reshape(2 * pairs, -1)
            if len(live) not in runs:
                runs[len(live)] = _runs(live % pairs, pairs)
            actions = np.empty((2, pairs, self.action_dim), dtype=np.float32)
            for start, stop in runs[len(live)]:
                run_offsets = [(weight[start:stop], bias[start:stop]) for weight, bias in offsets]
                actions[:, start:stop] = self.policy.mirrored(center, run_offsets, observations[:, start:stop])
            return actions.reshape(2 * pairs, -1)[live]

        return pairs_forward

    def _reset(self, worker: _Worker, batch: mujoco.batch.Batch, seeds: Sequence[int], first_obs: np.ndarray, x_before: np.ndarray) -> None:
        data = worker.reset_env.unwrapped.data
        row = np.empty(batch.nstate)
        for p, seed in enumerate(seeds):
            first_obs[p] = worker.reset_env.reset(seed=seed)[0]
            mujoco.mj_getState(worker.model, data, row, _INTEGRATION_STATE)
            batch.state[p] = row
            if self.x_body is not None:
                x_before[p] = data.xpos[self.x_body, 0]
            else:
                x_before[p] = data.qpos[0]

    def _contact_forces(self, worker: _Worker, batch: mujoco.batch.Batch, members: np.ndarray, out: np.ndarray) -> None:
        # mj_step does not compute cfrc_ext; gymnasium calls mj_rnePostConstraint after every step
        # on the MjData the step left behind, which only a persistent batch keeps.
        scratch = worker.scratch
        for p in members:
            batch.get_data(int(p), scratch)
            mujoco.mj_rnePostConstraint(worker.model, scratch)
            out[p] = scratch.cfrc_ext

    def _last_substep(self, worker: _Worker, state: np.ndarray, members: np.ndarray, cfrc_ext: np.ndarray, x_after: np.ndarray) -> None:
        """Each member's last substep of a step on ``worker``'s own MjData, from and back into its
        state row (as the batch loads and saves it), then gymnasium's mj_rnePostConstraint: its
        contact forces and the main body's x, without copying a whole MjData out of the batch."""
        model, scratch = worker.model, worker.scratch
        forces = scratch.cfrc_ext  # views of the MjData's own arrays
        x = scratch.xpos[self.x_body] if self.x_body is not None else scratch.qpos
        for p in members:
            row = state[p]
            mujoco.mj_setState(model, scratch, row, _INTEGRATION_STATE)
            mujoco.mj_step(model, scratch)
            mujoco.mj_rnePostConstraint(model, scratch)
            mujoco.mj_getState(model, scratch, row, _INTEGRATION_STATE)
            cfrc_ext[p] = forces
            x_after[p] = x[0]

    def _play(self, worker: _Worker, params: torch.Tensor, seeds: list[int], mirrored: Mirrored | None, chunk: _Chunk) -> dict[str, np.ndarray]:
        """One episode per member of ``chunk``, on ``worker``'s batch: the padded arrays of :meth:`rollout`."""
        population, horizon, rules, c = len(chunk.members), self.horizon, self.rules, self.constants
        batch = worker.batch(population, self.threads_per_batch, self.persistent)
        policy = self._policy(params, mirrored, chunk)
        nq, nv = self.model.nq, self.model.nv
        state_qpos = batch.bind("qpos")  # live views of the state rows
        state_qvel = batch.bind("qvel")
        ctrl = batch.bind("ctrl")
        x_body = self.x_body
        body_xpos = batch.bind("xpos") if x_body is not None else None

        episodes = self._padded(population)
        obs_traj, actions, rewards = episodes["obs_traj"], episodes["actions"], episodes["rewards"]
        terminated, truncated, lengths = episodes["terminated"], episodes["truncated"], episodes["lengths"]
        x_before = np.empty(population)
        first_obs = np.empty((population, self.observation_dim))
        cfrc_ext = np.zeros((population, self.model.nbody, 6)) if rules.contact_forces else None
        in_worker = self.last_substep_in_worker
        x_last = np.empty(population) if in_worker else None
        self._reset(worker, batch, seeds, first_obs, x_before)
        obs_traj[:, 0] = first_obs

        live = np.arange(population)
        skipped = self.skipped_qpos
        for t in range(horizon):
            all_live = len(live) == population
            # Basic slices while every member is live: views instead of fancy-index copies.
            rows = slice(None) if all_live else live
            action = policy(obs_traj[:, t], None if all_live else live)
            actions[rows, t] = action
            ctrl[rows] = action

            ids = None if all_live else live
            if in_worker:  # all substeps but the last on the batch
                if self.frame_skip > 1:
                    batch.step(ids=ids, nstep=self.frame_skip - 1)
                self._last_substep(worker, batch.state, live, cfrc_ext, x_last)
            else:
                batch.step(ids=ids, nstep=self.frame_skip)

            qpos, qvel = state_qpos[rows], state_qvel[rows]
            if in_worker:
                x_after = x_last[rows]
            elif x_body is not None:
                x_after = body_xpos[rows, x_body, 0]
            else:
                x_after = qpos[:, 0]
            forward_reward = c["_forward_reward_weight"] * ((x_after - x_before[rows]) / self.dt)
            x_before[rows] = x_after
            # float32 like gymnasium's np.sum(np.square(action)) on the float32 action
            ctrl_cost = self.ctrl_cost_weight * np.square(action).sum(axis=1)

            # A view while all are live; a fancy-index copy otherwise, written back below.
            observation = obs_traj[rows, t + 1]
            n_pos = nq - skipped
            observation[:, :n_pos] = qpos[:, skipped:]
            if rules.clip_qvel is None:
                observation[:, n_pos : n_pos + nv] = qvel
            else:
                observation[:, n_pos : n_pos + nv] = np.clip(qvel, -rules.clip_qvel, rules.clip_qvel)

            if rules.healthy is not None:
                healthy = rules.healthy(qpos, qvel, c)
                reward = forward_reward + healthy * c["_healthy_reward"]
                term = ~healthy if c["_terminate_when_unhealthy"] else np.zeros(len(live), dtype=bool)
            else:
                reward = forward_reward
                term = None
            if rules.contact_forces:
                if not in_worker:
                    self._contact_forces(worker, batch, live, cfrc_ext)
                low, high = c["_contact_force_range"]
                clipped = np.clip(cfrc_ext[rows], low, high)
                contact_cost = c["_contact_cost_weight"] * np.square(clipped).reshape(len(live), -1).sum(axis=1)
                if self.contact_forces_in_obs:
                    observation[:, n_pos + nv :] = clipped[:, 1:].reshape(len(live), -1)
                reward = reward - (ctrl_cost + contact_cost)
            else:
                reward = reward - ctrl_cost
            if not all_live:
                obs_traj[live, t + 1] = observation
            rewards[rows, t] = reward
            lengths[rows] = t + 1
            if t + 1 >= horizon:  # time limit (gymnasium's TimeLimit: truncated even when also terminated)
                truncated[rows, t] = True
            if term is not None and term.any():
                terminated[rows, t] = term
                if t + 1 >= horizon:
                    break
                live = live[~term]
                if len(live) == 0:
                    break

        return episodes
