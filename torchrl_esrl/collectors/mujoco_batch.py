"""Fast ES population evaluation on MuJoCo's batched executor (paper, Algorithm 1 "Evaluate").

:class:`MujocoBatchBackend` plays one episode per population member like the reference
``"gym"`` backend (:class:`torchrl_esrl.collectors.gym_backend.GymBackend`), but steps all members' physics
with one ``mujoco.batch.Batch.step`` call per env step (MuJoCo's own thread pool, no processes)
and recomputes observations, rewards, termination and truncation of the gymnasium v5 tasks in
vectorised numpy over the live members.

Why hand-written: gymnasium computes observations and rewards one env at a time from an
``MjData``; ``mujoco.batch`` gives the raw state of all simulations as one array but knows nothing
about the tasks. The formulas below are those of ``gymnasium/envs/mujoco/*_v5.py`` with their
default arguments (the constants are read from a gymnasium env of the task, so they cannot drift
from it); the tests check observations, actions, rewards and flags against gymnasium.

Initial states are gymnasium's own: one gymnasium env of the task is reset with each member's
seed and its whole integration state (``mj_getState(mjSTATE_INTEGRATION)``: time, qpos, qvel,
warm start, controls, ...) is copied into that member's row of the batch. This reproduces
``reset(seed=s)`` exactly without re-implementing each task's reset noise.
"""
from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import mujoco
import mujoco.batch
import numpy as np
import torch

from torchrl_esrl.collectors.generation import Generation, transitions_from_arrays
from torchrl_esrl.envs import make_gym_env, resolve_env_id
from torchrl_esrl.modules.networks import Mirrored, PopulationActor, one_blas_thread

_INTEGRATION_STATE = mujoco.mjtState.mjSTATE_INTEGRATION


@dataclass(frozen=True)
class TaskRules:
    """What one gymnasium v5 locomotion task computes after each physics step (defaults only)."""

    skipped_qpos: int  # leading qpos entries left out of the observation (x, or x and y)
    clip_qvel: float | None  # Walker2d and Hopper clip velocities in the observation
    x_from_body: int | None  # Ant measures progress on a body's xpos, the others on qpos[0]
    healthy: Callable[[np.ndarray, np.ndarray, dict], np.ndarray] | None  # (qpos, qvel, constants) -> [n] bool
    contact_forces: bool  # Ant: clipped cfrc_ext in the observation and a contact cost


def _walker2d_healthy(qpos, qvel, c):
    z, angle = qpos[:, 1], qpos[:, 2]
    (min_z, max_z), (min_a, max_a) = c["_healthy_z_range"], c["_healthy_angle_range"]
    return (min_z < z) & (z < max_z) & (min_a < angle) & (angle < max_a)


def _hopper_healthy(qpos, qvel, c):
    z, angle = qpos[:, 1], qpos[:, 2]
    min_s, max_s = c["_healthy_state_range"]
    (min_z, max_z), (min_a, max_a) = c["_healthy_z_range"], c["_healthy_angle_range"]
    state = np.concatenate([qpos[:, 2:], qvel], axis=1)
    healthy_state = ((min_s < state) & (state < max_s)).all(axis=1)
    return healthy_state & (min_z < z) & (z < max_z) & (min_a < angle) & (angle < max_a)


def _ant_healthy(qpos, qvel, c):
    min_z, max_z = c["_healthy_z_range"]
    finite = np.isfinite(qpos).all(axis=1) & np.isfinite(qvel).all(axis=1)
    return finite & (min_z <= qpos[:, 2]) & (qpos[:, 2] <= max_z)  # inclusive, as gymnasium's Ant


TASKS: dict[str, TaskRules] = {
    "HalfCheetah-v5": TaskRules(1, None, None, None, False),
    "Swimmer-v5": TaskRules(2, None, None, None, False),
    "Walker2d-v5": TaskRules(1, 10.0, None, _walker2d_healthy, False),
    "Hopper-v5": TaskRules(1, 10.0, None, _hopper_healthy, False),
    "Ant-v5": TaskRules(2, None, 1, _ant_healthy, True),
}

# Constants read from the gymnasium env, so the batch computes with gymnasium's own values.
_CONSTANTS = (
    "_forward_reward_weight", "_ctrl_cost_weight", "_healthy_reward", "_terminate_when_unhealthy",
    "_healthy_z_range", "_healthy_angle_range", "_healthy_state_range", "_contact_cost_weight",
    "_contact_force_range", "_main_body", "_exclude_current_positions_from_observation",
    "_include_cfrc_ext_in_observation",
)  # fmt: skip


class MujocoBatchBackend:
    """ES backend: all members' physics in one ``mujoco.batch.Batch``, one batched policy forward per step.

    Args:
        env_id: a gymnasium id in :data:`TASKS` (or its short name).
        population_actor: evaluates all members' actors at once.
        max_episode_steps: time limit (the env spec's when None).
        nthread: MuJoCo batch threads (default: all CPUs).
        persistent: keep one ``MjData`` per simulation (needed, and forced, for Ant's contact forces).
        compact_finished: run the policy forward on the live members only (their parameter rows
            are re-gathered when the live set shrinks to 3/4). Off by default: a batched matmul's
            rounding depends on the batch size (measured ~1e-6 differences), which chaotic tasks
            amplify into different episodes, so members would no longer get exactly the actions
            the reference ``"gym"`` backend (forward over all P) gives them.
        threaded_forward: run the policy forward as two contiguous halves of the population on
            two threads (numpy's einsum releases the GIL) from 16 members on (default). The
            forward over a contiguous block gives each member bit for bit the actions of the
            forward over all P (tests/test_networks.py), so the episodes are those of the
            one-thread loop. The physics always runs on all ``nthread`` MuJoCo threads.

    Given the population as :class:`~torchrl_esrl.modules.networks.Mirrored` pairs (OpenAI-ES),
    the forward is :meth:`PopulationActor.mirrored <torchrl_esrl.modules.networks.PopulationActor.mirrored>`
    over blocks of pairs: each pair's noise is read once per step for both members. Its actions
    equal the flat rows' up to float32 rounding (the rollout stays deterministic); the ``gym``
    reference computes the same forward when given the pairs.
    """

    name = "mujoco_batch"

    def __init__(
        self,
        env_id: str,
        population_actor: PopulationActor,
        max_episode_steps: int | None = None,
        nthread: int | None = None,
        persistent: bool = False,
        compact_finished: bool = False,
        threaded_forward: bool = True,
    ):
        self.env_id = resolve_env_id(env_id)
        if self.env_id not in TASKS:
            raise ValueError(f"mujoco_batch backend: unsupported env '{self.env_id}' (supported: {', '.join(TASKS)})")
        self.rules = TASKS[self.env_id]
        self.policy = population_actor
        # The reset env: its reset(seed) gives each member gymnasium's exact initial state.
        self.reset_env = make_gym_env(self.env_id, max_episode_steps)
        env = self.reset_env.unwrapped
        self.constants = {k: getattr(env, k) for k in _CONSTANTS if hasattr(env, k)}
        if not self.constants.get("_exclude_current_positions_from_observation", True):
            raise ValueError("mujoco_batch backend handles the default observation only")
        self.model = env.model
        self.frame_skip = int(env.frame_skip)
        self.dt = env.dt  # the same float gymnasium divides by
        self.horizon = int(max_episode_steps or self.reset_env.spec.max_episode_steps or 1000)
        self.observation_dim = int(np.prod(self.reset_env.observation_space.shape))
        self.action_dim = int(self.model.nu)
        self.nthread = int(nthread or os.cpu_count() or 1)
        self.persistent = bool(persistent or self.rules.contact_forces)
        self.compact_finished = bool(compact_finished)
        self.threaded_forward = bool(threaded_forward)
        self._forward_thread: ThreadPoolExecutor | None = None
        self.ctrl_cost_weight = np.float32(self.constants["_ctrl_cost_weight"])  # gymnasium multiplies a float32 sum
        self._batch: mujoco.batch.Batch | None = None
        self._scratch = mujoco.MjData(self.model) if self.rules.contact_forces else None

    @staticmethod
    def supports(env_id: str) -> bool:
        try:
            return resolve_env_id(env_id) in TASKS
        except Exception:  # noqa: BLE001 - unknown ids are simply not supported
            return False

    def _blocks(self, rows: int, members_per_row: int = 1) -> list[slice]:
        """The contiguous blocks of ``rows`` (members, or pairs of members) the forward runs on."""
        # Small populations (the 5-episode evaluations) gain nothing from a thread hand-off.
        if not self.threaded_forward or rows * members_per_row < 16:
            return [slice(0, rows)]
        return [slice(0, rows // 2), slice(rows // 2, rows)]

    def _forward_blocks(self, params: torch.Tensor) -> list[tuple[slice, list]]:
        """The member blocks of the forward, with their parameter views."""
        return [(block, self.policy.split(params[block])) for block in self._blocks(params.shape[0])]

    def _mirrored_blocks(self, mirrored: Mirrored) -> list[tuple[slice, list, list]]:
        """The pair blocks of the mirrored forward, with the center's and the offsets' views."""
        return [(block, *self.policy.split_pairs(mirrored, block)) for block in self._blocks(mirrored.offsets.shape[0], 2)]

    def _in_blocks(self, forward: Callable, blocks: list) -> None:
        """``forward(*block)`` for every block: the second on a worker thread during the first
        (numpy releases the GIL in its kernels)."""
        if len(blocks) == 1:
            forward(*blocks[0])
            return
        if self._forward_thread is None:
            self._forward_thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="population-forward")
        pending = self._forward_thread.submit(forward, *blocks[1])
        forward(*blocks[0])
        pending.result()

    def _forward(self, params: torch.Tensor, observations: torch.Tensor, blocks) -> np.ndarray:
        """Actions of all members of ``params`` on ``observations`` [P, obs]."""
        actions = np.empty((params.shape[0], self.action_dim), dtype=np.float32)

        def forward(block, layers):
            actions[block] = self.policy(params[block], observations[block], layers).numpy()

        self._in_blocks(forward, blocks)
        return actions

    def _forward_mirrored(self, observations: np.ndarray, blocks) -> np.ndarray:
        """Actions of all members of mirrored pairs on ``observations`` [2K, obs] (members k, K + k)."""
        pairs = blocks[-1][0].stop
        pair_observations = observations.reshape(2, pairs, -1)
        actions = np.empty((2, pairs, self.action_dim), dtype=np.float32)

        def forward(block, center, offsets):
            actions[:, block] = self.policy.mirrored(center, offsets, pair_observations[:, block])

        self._in_blocks(forward, blocks)
        return actions.reshape(2 * pairs, -1)

    def _get_batch(self, population: int) -> mujoco.batch.Batch:
        if self._batch is None or self._batch.nsim != population:
            self._batch = mujoco.batch.Batch(self.model, population, min(self.nthread, population), self.persistent)
        return self._batch

    def _reset(self, batch: mujoco.batch.Batch, seeds: Sequence[int], first_obs: np.ndarray, x_before: np.ndarray) -> None:
        data = self.reset_env.unwrapped.data
        row = np.empty(batch.nstate)
        for p, seed in enumerate(seeds):
            first_obs[p] = self.reset_env.reset(seed=int(seed))[0]
            mujoco.mj_getState(self.model, data, row, _INTEGRATION_STATE)
            batch.state[p] = row
            if self.rules.x_from_body is not None:
                x_before[p] = data.xpos[self.rules.x_from_body, 0]
            else:
                x_before[p] = data.qpos[0]

    def _contact_forces(self, batch: mujoco.batch.Batch, members: np.ndarray, out: np.ndarray) -> None:
        # mj_step does not compute cfrc_ext; gymnasium calls mj_rnePostConstraint after every step
        # on the MjData the step left behind, which only a persistent batch keeps.
        scratch = self._scratch
        for p in members:
            batch.get_data(int(p), scratch)
            mujoco.mj_rnePostConstraint(self.model, scratch)
            out[p] = scratch.cfrc_ext

    @torch.no_grad()
    def rollout(self, params: torch.Tensor, seeds: Sequence[int], mirrored: Mirrored | None = None) -> Generation:
        """One episode per row of ``params``; with ``mirrored`` (the same population as pairs) the
        forward reads each pair's noise once (not with ``compact_finished``)."""
        with one_blas_thread():
            return self._rollout(params, seeds, None if self.compact_finished else mirrored)

    def _rollout(self, params: torch.Tensor, seeds: Sequence[int], mirrored: Mirrored | None) -> Generation:
        population, horizon, rules, c = params.shape[0], self.horizon, self.rules, self.constants
        batch = self._get_batch(population)
        nq, nv = self.model.nq, self.model.nv
        state_qpos = batch.bind("qpos")  # live views of the state rows
        state_qvel = batch.bind("qvel")
        ctrl = batch.bind("ctrl")
        body_xpos = batch.bind("xpos") if rules.x_from_body is not None else None

        # Padded outputs, written in place. One observation trajectory per member serves as both
        # "observation" (steps 0..T-1) and "next/observation" (steps 1..T): no duplicate copies.
        obs_traj = np.zeros((population, horizon + 1, self.observation_dim), dtype=np.float32)
        actions = np.zeros((population, horizon, self.action_dim), dtype=np.float32)
        rewards = np.zeros((population, horizon))
        terminated = np.zeros((population, horizon), dtype=bool)
        truncated = np.zeros((population, horizon), dtype=bool)
        lengths = np.zeros(population, dtype=np.int64)
        x_before = np.empty(population)
        first_obs = np.empty((population, self.observation_dim))
        cfrc_ext = np.zeros((population, self.model.nbody, 6)) if rules.contact_forces else None
        self._reset(batch, seeds, first_obs, x_before)
        obs_traj[:, 0] = first_obs

        live = np.arange(population)
        # Members whose parameters the forward runs on: all of them, or with compact_finished a
        # group re-gathered (one copy of its rows) only when the live set has shrunk to 3/4 of it,
        # so finished members cost a little wasted forward instead of one P x D copy each.
        group, group_params = live, params
        blocks = self._forward_blocks(group_params) if mirrored is None else self._mirrored_blocks(mirrored)
        position_in_group = live  # row of each live member in group_params
        skipped = rules.skipped_qpos
        for t in range(horizon):
            if self.compact_finished and len(live) * 4 <= len(group) * 3:
                group, group_params = live, params[torch.as_tensor(live)]
                blocks = self._forward_blocks(group_params)
                position_in_group = np.arange(len(live))
            all_live = len(live) == population
            # Basic slices while every member is live: views instead of fancy-index copies.
            rows = slice(None) if all_live else live
            group_rows = slice(None) if len(group) == population else group
            if mirrored is None:
                action = self._forward(group_params, torch.from_numpy(obs_traj[group_rows, t]), blocks)
            else:  # all members, every step (compact_finished is off)
                action = self._forward_mirrored(obs_traj[:, t], blocks)
            if len(group) != len(live):
                action = action[position_in_group]
            actions[rows, t] = action
            ctrl[rows] = action

            batch.step(ids=None if all_live else live, nstep=self.frame_skip)

            qpos, qvel = state_qpos[rows], state_qvel[rows]
            if rules.x_from_body is not None:
                x_after = body_xpos[rows, rules.x_from_body, 0]
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
                self._contact_forces(batch, live, cfrc_ext)
                low, high = c["_contact_force_range"]
                clipped = np.clip(cfrc_ext[rows], low, high)
                contact_cost = c["_contact_cost_weight"] * np.square(clipped).reshape(len(live), -1).sum(axis=1)
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
                position_in_group = np.searchsorted(group, live)

        returns = rewards.sum(axis=1)
        transitions = transitions_from_arrays(
            obs_traj[:, :-1], actions, obs_traj[:, 1:], rewards, terminated, truncated, lengths, returns
        )
        return Generation(torch.as_tensor(returns), torch.as_tensor(lengths), transitions)
