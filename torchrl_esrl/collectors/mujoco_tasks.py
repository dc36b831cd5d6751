"""The gymnasium v5 MuJoCo locomotion tasks as :class:`~torchrl_esrl.collectors.mujoco_batch.MujocoBatchBackend`
computes them: per task, what ``gymnasium/envs/mujoco/*_v5.py`` computes after each physics step
(:data:`TASKS`), the constructor keywords whose effect the backend reproduces, and why an
:class:`~torchrl_esrl.envs.EnvSpec` asks for something it does not compute (the refusals that
hand the ES physics back to the ``gym`` reference).
"""
from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

from torchrl_esrl.envs import EnvSpec, as_env_spec
from torchrl_esrl.torchrl_private import gym_mujoco_constants


@dataclass(frozen=True)
class TaskRules:
    """What one gymnasium v5 locomotion task computes after each physics step; the settings it
    reads come from the gymnasium env (:func:`~torchrl_esrl.torchrl_private.gym_mujoco_constants`)."""

    skipped_qpos: int  # leading qpos entries left out of the observation (x, or x and y) unless
    # exclude_current_positions_from_observation=False
    clip_qvel: float | None  # Walker2d and Hopper clip velocities in the observation
    x_from_main_body: bool  # Ant measures progress on the xpos of its main_body, the others on qpos[0]
    healthy: Callable[[np.ndarray, np.ndarray, dict], np.ndarray] | None  # (qpos, qvel, constants) -> [n] bool
    contact_forces: bool  # Ant: a contact cost, and clipped cfrc_ext in the observation unless
    # include_cfrc_ext_in_observation=False


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
    "HalfCheetah-v5": TaskRules(1, None, False, None, False),
    "Swimmer-v5": TaskRules(2, None, False, None, False),
    "Walker2d-v5": TaskRules(1, 10.0, False, _walker2d_healthy, False),
    "Hopper-v5": TaskRules(1, 10.0, False, _hopper_healthy, False),
    "Ant-v5": TaskRules(2, None, True, _ant_healthy, True),
}

# Keyword arguments of the v5 constructors (``env.kwargs``) whose effect the backend reproduces:
# it reads each back from the gymnasium env it builds, or it only changes gymnasium's own reset,
# which the backend replays.
REPRODUCED_KWARGS = frozenset({
    "frame_skip",  # env.frame_skip (physics steps per step) and env.dt
    "forward_reward_weight", "ctrl_cost_weight", "contact_cost_weight", "healthy_reward",
    "terminate_when_unhealthy", "healthy_z_range", "healthy_angle_range", "healthy_state_range",
    "contact_force_range",  # the env's constants, as its step reads them
    "main_body",  # the body id gymnasium's data.body(main_body) resolves
    "exclude_current_positions_from_observation", "include_cfrc_ext_in_observation",  # the observation layout
    "reset_noise_scale",  # gymnasium's reset
    "xml_file",  # only the task's own model file (another model is refused)
})  # fmt: skip
# MujocoEnv's rendering settings: no observation, reward or flag depends on them; render_mode
# "human" is refused (gymnasium renders at every reset and step).
RENDERING_KWARGS = frozenset({"render_mode", "width", "height", "camera_id", "camera_name", "default_camera_config", "max_geom", "visual_options"})


def spec_refusals(spec: EnvSpec) -> list[str]:
    """What the spec asks that the backend does not compute, from the spec alone."""
    if spec.id not in TASKS:
        return [f"env.id: {spec.id} is not a task it knows ({', '.join(TASKS)})"]
    reasons = []
    for key, value in spec.kwargs.items():
        if key not in REPRODUCED_KWARGS | RENDERING_KWARGS:
            reasons.append(f"env.kwargs.{key}={value!r}: not a keyword it reproduces")
        elif key == "render_mode" and value == "human":
            reasons.append(f"env.kwargs.{key}={value!r}: gymnasium renders at every step")
    return reasons + [change for change in spec.changes() if not change.startswith("env.kwargs.")]


def observation_layout(rules: TaskRules, constants: dict, model: mujoco.MjModel) -> tuple[int, bool, int]:
    """(qpos entries skipped, contact forces included, observation size) as the env's
    ``_get_obs`` builds the observation."""
    skipped = rules.skipped_qpos if constants["_exclude_current_positions_from_observation"] else 0
    contact_forces = rules.contact_forces and bool(constants["_include_cfrc_ext_in_observation"])
    return skipped, contact_forces, model.nq - skipped + model.nv + (6 * (model.nbody - 1) if contact_forces else 0)


def env_refusals(spec: EnvSpec, gym_env) -> list[str]:
    """What the gymnasium env built from ``spec`` computes that the backend would not."""
    env, rules = gym_env.unwrapped, TASKS[spec.id]
    constants = gym_mujoco_constants(env)
    reasons = []
    if "xml_file" in spec.kwargs:
        own = as_env_spec(spec.id).make_gym()
        try:
            if not os.path.samefile(env.fullpath, own.unwrapped.fullpath):
                reasons.append(f"env.kwargs.xml_file={spec.kwargs['xml_file']!r}: another model than {spec.id}'s, the one its rules are checked on")
        finally:
            own.close()
    if rules.x_from_main_body:
        try:
            env.data.body(constants["_main_body"])
        except (IndexError, KeyError, TypeError) as error:
            reasons.append(f"env.kwargs.main_body={constants['_main_body']!r}: not a body of the model ({str(error).splitlines()[0]})")
    size = int(np.prod(env.observation_space.shape))
    expected = observation_layout(rules, constants, env.model)[2]
    if size != expected:
        reasons.append(f"env.kwargs: an observation of {size} entries, not the {expected} of {spec.id}'s layout")
    return reasons
