"""The mujoco_batch ES backend reproduces gymnasium v5 episodes, on real MuJoCo physics."""
from __future__ import annotations

import os

import gymnasium as gym
import gymnasium.envs.mujoco
import mujoco
import numpy as np
import pytest
import torch
from torchrl.data import Bounded

from torchrl_esrl.data.multibuffer import TRANSITION_KEYS
from torchrl_esrl.collectors.backends import backend_class, default_backend
from torchrl_esrl.collectors.es_collector import ESCollector
from torchrl_esrl.collectors.gym_backend import GymBackend
from torchrl_esrl.collectors.mujoco_batch import RENDERING_KWARGS, REPRODUCED_KWARGS, MujocoBatchBackend
from torchrl_esrl.envs import EnvSpec, as_env_spec, constructor_keywords
from torchrl_esrl.es.openes import OpenES
from torchrl_esrl.modules.networks import flat_parameters, make_actor
from torchrl_esrl.modules.population import PopulationActor

ENV_IDS = ["HalfCheetah-v5", "Walker2d-v5", "Ant-v5", "Swimmer-v5", "Hopper-v5"]
TERMINATING = {"Walker2d-v5", "Ant-v5", "Hopper-v5"}
KEYS = [*TRANSITION_KEYS, "episode_return", ("collector", "traj_ids")]


def population(env: "str | EnvSpec", members: int, sigma: float, seed: int = 0):
    """A random 2x256 tanh actor of the task (an id or a spec) and ``members`` Gaussian
    perturbations of it (wide ones fall early)."""
    env = as_env_spec(env).make_gym()
    torch.manual_seed(seed)
    low, high = torch.as_tensor(env.action_space.low), torch.as_tensor(env.action_space.high)
    actor = make_actor(env.observation_space.shape[0], Bounded(low, high, shape=low.shape))
    theta = flat_parameters(actor)
    params = theta + sigma * torch.randn(members, theta.numel())
    return PopulationActor(actor), params.contiguous()


@pytest.mark.parametrize("workers", [2, 1])
@pytest.mark.parametrize("env_id", ENV_IDS)
def test_same_episodes_as_gym_backend(env_id, workers):
    steps, members = 120, 16 if workers == 2 else 6
    policy, params = population(env_id, members, sigma=0.3)
    seeds = [11 * p + 3 for p in range(members)]
    reference = GymBackend(env_id, policy, max_episode_steps=steps).rollout(params, seeds)
    batched = MujocoBatchBackend(env_id, policy, max_episode_steps=steps, nthread=2, workers=workers).rollout(params, seeds)

    assert torch.equal(batched.lengths, reference.lengths)
    torch.testing.assert_close(batched.returns, reference.returns, rtol=1e-6, atol=1e-6)
    assert batched.transitions.batch_size == reference.transitions.batch_size
    for key in KEYS:
        torch.testing.assert_close(batched.transitions.get(key), reference.transitions.get(key), rtol=1e-5, atol=1e-5)
    if env_id in TERMINATING:  # the early-termination path was exercised
        assert (reference.lengths < steps).any()
    else:
        assert (reference.lengths == steps).all()


class ScriptedActions:
    """Stands in for the population actor: plays a fixed action sequence, step after step."""

    def __init__(self, actions: np.ndarray):
        self.actions = torch.as_tensor(actions)  # [P, T, action_dim]
        self.t = 0

    def split(self, params):
        return None

    def __call__(self, params, observations, layers=None):
        action = self.actions[:, self.t]
        self.t += 1
        return action[: observations.shape[0]]


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_fixed_actions_match_a_raw_gymnasium_loop(env_id):
    steps, members = 60, 3
    env = gym.make(env_id, max_episode_steps=steps)
    rng = np.random.default_rng(7)
    # Large actions make Walker2d/Hopper/Ant fall within the budget.
    actions = rng.uniform(env.action_space.low, env.action_space.high, (members, steps, env.action_space.shape[0]))
    actions = actions.astype(np.float32)
    seeds = [5, 6, 7]
    # One chunk: one policy call per step.
    backend = MujocoBatchBackend(env_id, ScriptedActions(actions), max_episode_steps=steps, workers=1, chunks_per_worker=1)
    generation = backend.rollout(torch.zeros(members, 1), seeds)
    traj_ids = generation.transitions.get(("collector", "traj_ids"))

    for p, seed in enumerate(seeds):
        obs, _ = env.reset(seed=seed)
        observations, rewards, terminated, truncated = [obs], [], [], []
        for t in range(steps):
            obs, reward, term, trunc, _ = env.step(actions[p, t])
            observations.append(obs)
            rewards.append(reward)
            terminated.append(term)
            truncated.append(trunc)
            if term or trunc:
                break
        length = len(rewards)
        mine = generation.transitions[traj_ids == p]
        assert int(generation.lengths[p]) == length == mine.batch_size[0]
        expected_obs = torch.as_tensor(np.array(observations), dtype=torch.float32)
        torch.testing.assert_close(mine.get("observation"), expected_obs[:-1], rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(mine.get(("next", "observation")), expected_obs[1:], rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(mine.get("action"), torch.as_tensor(actions[p, :length]))
        torch.testing.assert_close(
            mine.get(("next", "reward")).squeeze(-1), torch.as_tensor(rewards, dtype=torch.float32), rtol=1e-6, atol=1e-6
        )
        assert mine.get(("next", "terminated")).squeeze(-1).tolist() == terminated
        assert mine.get(("next", "truncated")).squeeze(-1).tolist() == truncated
        assert float(generation.returns[p]) == pytest.approx(float(np.sum(rewards)), rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("env_id", ["Walker2d-v5", "Hopper-v5"])
def test_early_terminated_members_contribute_only_their_steps(env_id):
    steps, members = 150, 8
    policy, params = population(env_id, members, sigma=0.3, seed=1)
    generation = MujocoBatchBackend(env_id, policy, max_episode_steps=steps).rollout(params, list(range(members)))
    lengths = generation.lengths
    assert (lengths < steps).any() and len(set(lengths.tolist())) > 1  # members end at different steps
    traj_ids = generation.transitions.get(("collector", "traj_ids"))
    assert generation.transitions.batch_size[0] == generation.frames == int(lengths.sum())
    assert torch.equal(torch.bincount(traj_ids, minlength=members), lengths)
    assert torch.equal(traj_ids, torch.repeat_interleave(torch.arange(members), lengths))  # member-major
    done = generation.transitions.get(("next", "done")).squeeze(-1)
    terminated = generation.transitions.get(("next", "terminated")).squeeze(-1)
    last = torch.cumsum(lengths, 0) - 1
    assert done[last].all() and int(done.sum()) == members  # done only on each member's last step
    assert torch.equal(terminated[last], lengths < steps) and int(terminated.sum()) == int((lengths < steps).sum())
    rewards = generation.transitions.get(("next", "reward")).squeeze(-1).double()
    per_member = torch.zeros(members, dtype=torch.float64).index_add_(0, traj_ids, rewards)
    torch.testing.assert_close(per_member, generation.returns, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("env_id", ["HalfCheetah-v5", "Walker2d-v5", "Hopper-v5"])
def test_chunks_and_workers_give_the_one_chunk_episodes_bit_for_bit(env_id):
    """Two workers on uneven chunks (an odd population) produce exactly the generation of one
    chunk on one thread, early terminations included."""
    steps, members = 150, 17
    policy, params = population(env_id, members, sigma=0.3, seed=2)
    seeds = list(range(40, 40 + members))
    one = MujocoBatchBackend(env_id, policy, max_episode_steps=steps, nthread=1, workers=1, chunks_per_worker=1)
    chunked = MujocoBatchBackend(env_id, policy, max_episode_steps=steps, nthread=2, workers=2, chunks_per_worker=3, min_chunk=1)
    assert [len(chunk.members) for chunk in chunked.chunks(members)] == [3, 3, 3, 3, 3, 2]
    sequential, threaded = one.rollout(params, seeds), chunked.rollout(params, seeds)
    assert torch.equal(threaded.lengths, sequential.lengths)
    assert torch.equal(threaded.returns, sequential.returns)
    for key in KEYS:
        assert torch.equal(threaded.transitions.get(key), sequential.transitions.get(key)), key
    if env_id != "HalfCheetah-v5":
        assert (sequential.lengths < steps).any() and len(set(sequential.lengths.tolist())) > 1  # chunks end at different steps


@pytest.mark.parametrize("workers", [2, 1])
@pytest.mark.parametrize("env_id", ["HalfCheetah-v5", "Walker2d-v5"])
def test_mirrored_forward_gives_the_episodes_of_the_flat_rows(env_id, workers):
    """An OpenAI-ES population evaluated through its mirrored pairs plays the gym reference's
    episodes with the same forward; chunks of pairs on two workers or one chunk on one, bit for
    bit. (The pairs' forward equals the flat rows' up to float32 rounding:
    tests/test_population.py.)"""
    steps, members = 120, 18
    policy, params = population(env_id, members, sigma=0.3)
    es = OpenES(params[0].clone(), population_size=members, sigma=0.3, generator=torch.Generator().manual_seed(4))
    params = es.ask()
    seeds = [7 * p + 1 for p in range(members)]
    reference = GymBackend(env_id, policy, max_episode_steps=steps).rollout(params, seeds, mirrored=es.mirrored(params))
    backend = MujocoBatchBackend(env_id, policy, max_episode_steps=steps, nthread=2, workers=workers, chunks_per_worker=workers, min_chunk=2)
    mirrored = backend.rollout(params, seeds, mirrored=es.mirrored(params))
    assert torch.equal(mirrored.lengths, reference.lengths)
    torch.testing.assert_close(mirrored.returns, reference.returns, rtol=1e-6, atol=1e-6)
    for key in KEYS:
        torch.testing.assert_close(mirrored.transitions.get(key), reference.transitions.get(key), rtol=1e-5, atol=1e-5)
    flat = backend.rollout(params, seeds)
    assert not torch.equal(flat.transitions.get("action"), mirrored.transitions.get("action"))  # the pairs' forward was used
    other = MujocoBatchBackend(env_id, policy, max_episode_steps=steps, nthread=2, workers=3 - workers, chunks_per_worker=1)
    assert torch.equal(other.rollout(params, seeds, mirrored=es.mirrored(params)).returns, mirrored.returns)
    chunks = backend.chunks(members, es.mirrored(params))
    assert len(chunks) == workers**2
    for chunk in chunks:  # whole pairs: member k with member K + k
        pairs = np.arange(chunk.pairs.start, chunk.pairs.stop)
        assert np.array_equal(chunk.members, np.concatenate([pairs, members // 2 + pairs]))
    if env_id == "Walker2d-v5":
        assert (reference.lengths < steps).any()


def test_forward_on_the_live_pairs_gives_the_whole_chunk_forward_bit_for_bit():
    """Once pairs have finished, a chunk computes the pairs with a live member only (runs of
    contiguous pairs): every action equals bit for bit the forward over all the chunk's pairs on
    the same padded observations, and the episodes of chunks of one pair each."""
    steps, members = 150, 16
    policy, params = population("Walker2d-v5", members, sigma=0.3, seed=3)
    es = OpenES(params[0].clone(), population_size=members, sigma=0.5, generator=torch.Generator().manual_seed(5))
    params = es.ask()
    mirrored, seeds, pairs = es.mirrored(params), [3 * p + 2 for p in range(members)], members // 2
    one_chunk = MujocoBatchBackend("Walker2d-v5", policy, max_episode_steps=steps, nthread=1, workers=1, chunks_per_worker=1)
    generation = one_chunk.rollout(params, seeds, mirrored)
    lengths = generation.lengths.numpy()
    pair_ends = np.maximum(lengths[:pairs], lengths[pairs:])
    assert (pair_ends < pair_ends.max()).sum() >= 2 and len(set(pair_ends.tolist())) > 2  # pairs finished apart, before the chunk

    obs_traj = np.zeros((members, steps + 1, one_chunk.observation_dim), dtype=np.float32)  # the backend's padded layout
    actions = np.zeros((members, steps, one_chunk.action_dim), dtype=np.float32)
    traj_ids, observation = generation.transitions.get(("collector", "traj_ids")).numpy(), generation.transitions.get("observation").numpy()
    step = np.arange(len(traj_ids)) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    obs_traj[traj_ids, step], actions[traj_ids, step] = observation, generation.transitions.get("action").numpy()
    center, offsets = policy.split_pairs(mirrored)
    for t in range(int(lengths.max())):
        whole = policy.mirrored(center, offsets, obs_traj[:, t].reshape(2, pairs, -1)).reshape(members, -1)
        live = lengths > t
        assert np.array_equal(whole[live], actions[live, t]), t

    single_pairs = MujocoBatchBackend("Walker2d-v5", policy, max_episode_steps=steps, nthread=1, workers=1, chunks_per_worker=pairs, min_chunk=1)
    assert len(single_pairs.chunks(members, mirrored)) == pairs
    alone = single_pairs.rollout(params, seeds, mirrored)
    assert torch.equal(alone.lengths, generation.lengths) and torch.equal(alone.returns, generation.returns)
    for key in KEYS:
        assert torch.equal(alone.transitions.get(key), generation.transitions.get(key)), key


def test_ant_contact_forces_bit_for_bit_on_a_batch_of_one_thread_and_of_two():
    """Ant's clipped contact forces in the observation, and its contact cost, equal gymnasium's bit
    for bit whether each step's last substep runs on the worker's own MjData (a batch of one
    thread) or the batch keeps one MjData per simulation (a batch of two threads)."""
    steps, members = 40, 4
    policy, params = population("Ant-v5", members, sigma=0.3)
    seeds = [5 * p + 1 for p in range(members)]
    in_worker = MujocoBatchBackend("Ant-v5", policy, max_episode_steps=steps, nthread=1, workers=1)
    persistent = MujocoBatchBackend("Ant-v5", policy, max_episode_steps=steps, nthread=2, workers=1)
    assert in_worker.last_substep_in_worker and not in_worker.persistent
    assert not persistent.last_substep_in_worker and persistent.persistent and persistent.threads_per_batch == 2
    reference = _episodes(GymBackend("Ant-v5", policy, max_episode_steps=steps).rollout(params, seeds))
    forces = reference[("next", "observation")][:, in_worker.model.nq - 2 + in_worker.model.nv :]
    assert (forces != 0).any(axis=1).float().mean() > 0.2  # contact forces in many observations
    for backend in (in_worker, persistent):
        assert _equal(_episodes(backend.rollout(params, seeds)), reference)


def test_chunk_counts():
    """Up to two chunks per worker, of at least ``min_chunk`` members unless a worker would idle."""
    policy, _ = population("HalfCheetah-v5", 2, sigma=0.0)
    backend = MujocoBatchBackend("HalfCheetah-v5", policy, nthread=2)  # two workers, two chunks each, min_chunk 16
    assert [len(c.members) for c in backend.chunks(120)] == [30] * 4
    assert [len(c.members) for c in backend.chunks(40)] == [20, 20]
    assert [len(c.members) for c in backend.chunks(5)] == [3, 2]
    assert [len(c.members) for c in backend.chunks(1)] == [1]
    one = MujocoBatchBackend("HalfCheetah-v5", policy, nthread=1)
    assert len(one.workers) == 1 and [len(c.members) for c in one.chunks(120)] == [60, 60]


def test_registered_and_chosen_by_default():
    assert backend_class("mujoco_batch") is MujocoBatchBackend
    for env_id in ENV_IDS:
        assert default_backend(env_id) == "mujoco_batch"
    assert default_backend("Pendulum-v1") == "gym"
    assert default_backend("InvertedPendulum-v5") == "gym"
    policy, params = population("HalfCheetah-v5", 2, sigma=0.0)
    env = gym.make("HalfCheetah-v5")
    low, high = torch.as_tensor(env.action_space.low), torch.as_tensor(env.action_space.high)
    actor = make_actor(17, Bounded(low, high, shape=low.shape))
    collector = ESCollector("halfcheetah", actor, max_episode_steps=20, seed=3)
    assert isinstance(collector.backend, MujocoBatchBackend)
    generation = collector.evaluate(params[:, : collector.population_actor.num_parameters])
    assert generation.frames == 40 and collector.frames == 40


# One line per (task, keyword arguments, outcome). The first keyword is the case's: REFUSED names
# it in the refusal; CHANGES plays the gym reference's episodes bit for bit, and they differ from
# those of the spec without that keyword (a keyword both backends ignored would fail here);
# SAME plays them bit for bit, and they equal those without it (rendering settings, defaults).
CHANGES, SAME, REFUSED = "changes", "same", "refused"
ASSETS = os.path.join(os.path.dirname(gymnasium.envs.mujoco.__file__), "assets")
KWARG_CASES = [
    ("HalfCheetah-v5", {"frame_skip": 2}, CHANGES),
    ("HalfCheetah-v5", {"forward_reward_weight": 2.0}, CHANGES),
    ("HalfCheetah-v5", {"ctrl_cost_weight": 0.5}, CHANGES),
    ("HalfCheetah-v5", {"reset_noise_scale": 0.5}, CHANGES),
    ("HalfCheetah-v5", {"exclude_current_positions_from_observation": False}, CHANGES),
    ("HalfCheetah-v5", {"xml_file": "half_cheetah.xml"}, SAME),
    ("HalfCheetah-v5", {"xml_file": os.path.join(ASSETS, "half_cheetah.xml")}, SAME),
    ("HalfCheetah-v5", {"xml_file": "hopper.xml"}, REFUSED),
    ("HalfCheetah-v5", {"render_mode": "rgb_array"}, SAME),
    ("HalfCheetah-v5", {"render_mode": "human"}, REFUSED),
    ("HalfCheetah-v5", {"width": 64, "height": 48}, SAME),
    ("HalfCheetah-v5", {"camera_id": 0}, SAME),
    ("HalfCheetah-v5", {"camera_name": "track"}, SAME),
    ("HalfCheetah-v5", {"default_camera_config": {"distance": 2.0}}, SAME),
    ("HalfCheetah-v5", {"max_geom": 10}, SAME),
    ("HalfCheetah-v5", {"visual_options": {int(mujoco.mjtVisFlag.mjVIS_CONTACTPOINT): True}}, SAME),
    ("HalfCheetah-v5", {"disable_env_checker": True}, REFUSED),  # gymnasium.make's, not the task's
    ("HalfCheetah-v5", {"max_episode_steps": 60}, SAME),  # the spec's own time limit (KWARG_STEPS): one value; another is refused (tests/test_envs.py)
    ("Swimmer-v5", {"forward_reward_weight": 3.0}, CHANGES),
    ("Swimmer-v5", {"ctrl_cost_weight": 1.0}, CHANGES),
    ("Swimmer-v5", {"reset_noise_scale": 0.5}, CHANGES),
    ("Swimmer-v5", {"frame_skip": 2}, CHANGES),
    ("Swimmer-v5", {"exclude_current_positions_from_observation": False}, CHANGES),
    ("Walker2d-v5", {"frame_skip": 2}, CHANGES),
    ("Walker2d-v5", {"forward_reward_weight": 0.5}, CHANGES),
    ("Walker2d-v5", {"ctrl_cost_weight": 0.1}, CHANGES),
    ("Walker2d-v5", {"healthy_reward": 2.0}, CHANGES),
    ("Walker2d-v5", {"healthy_z_range": (1.2, 2.0)}, CHANGES),
    ("Walker2d-v5", {"healthy_angle_range": (-0.2, 0.2)}, CHANGES),
    ("Walker2d-v5", {"terminate_when_unhealthy": False, "healthy_z_range": (1.2, 2.0)}, CHANGES),
    ("Walker2d-v5", {"reset_noise_scale": 0.1}, CHANGES),
    ("Walker2d-v5", {"exclude_current_positions_from_observation": False}, CHANGES),
    ("Walker2d-v5", {"xml_file": "walker2d.xml"}, REFUSED),  # the v4 model
    ("Hopper-v5", {"frame_skip": 3}, CHANGES),
    ("Hopper-v5", {"forward_reward_weight": 2.0}, CHANGES),
    ("Hopper-v5", {"ctrl_cost_weight": 0.1}, CHANGES),
    ("Hopper-v5", {"healthy_reward": 0.5}, CHANGES),
    ("Hopper-v5", {"healthy_state_range": (-1.0, 1.0)}, CHANGES),
    ("Hopper-v5", {"healthy_z_range": (1.2, float("inf"))}, CHANGES),
    ("Hopper-v5", {"healthy_angle_range": (-0.05, 0.05)}, CHANGES),
    ("Hopper-v5", {"terminate_when_unhealthy": False, "healthy_angle_range": (-0.05, 0.05)}, CHANGES),
    ("Hopper-v5", {"reset_noise_scale": 0.05}, CHANGES),
    ("Hopper-v5", {"exclude_current_positions_from_observation": False}, CHANGES),
    ("Ant-v5", {"main_body": 4}, CHANGES),
    ("Ant-v5", {"main_body": "aux_1"}, CHANGES),
    ("Ant-v5", {"main_body": "front_left_leg"}, SAME),  # its frame is the torso's
    ("Ant-v5", {"main_body": "torso"}, SAME),
    ("Ant-v5", {"main_body": 14}, REFUSED),
    ("Ant-v5", {"main_body": "tail"}, REFUSED),
    ("Ant-v5", {"include_cfrc_ext_in_observation": False}, CHANGES),
    ("Ant-v5", {"exclude_current_positions_from_observation": False}, CHANGES),
    ("Ant-v5", {"contact_cost_weight": 0.05}, CHANGES),
    ("Ant-v5", {"contact_force_range": (-0.1, 0.1)}, CHANGES),
    ("Ant-v5", {"ctrl_cost_weight": 0.1}, CHANGES),
    ("Ant-v5", {"forward_reward_weight": 2.0}, CHANGES),
    ("Ant-v5", {"healthy_reward": 2.0}, CHANGES),
    ("Ant-v5", {"healthy_z_range": (0.6, 1.0)}, CHANGES),
    ("Ant-v5", {"terminate_when_unhealthy": False, "healthy_z_range": (0.6, 1.0)}, CHANGES),
    ("Ant-v5", {"frame_skip": 3}, CHANGES),
    ("Ant-v5", {"reset_noise_scale": 0.3}, CHANGES),
]
KWARG_STEPS, KWARG_MEMBERS = 60, 4
KWARG_SEEDS = [13 * p + 2 for p in range(KWARG_MEMBERS)]


def _case_id(case) -> str:
    env_id, kwargs, outcome = case
    shown = {key: value.replace(ASSETS, "ASSETS") if isinstance(value, str) else value for key, value in kwargs.items()}
    return f"{env_id.split('-')[0]}-" + ",".join(f"{key}={value}" for key, value in shown.items()) + f"-{outcome}"


def _episodes(generation) -> dict:
    return {"lengths": generation.lengths, "returns": generation.returns, **{key: generation.transitions.get(key) for key in KEYS}}


def _equal(a: dict, b: dict) -> bool:
    return all(a[key].shape == b[key].shape and torch.equal(a[key], b[key]) for key in a)


_BATCHED: dict[str, dict] = {}


def _batched_episodes(env_id: str, kwargs: dict) -> dict:
    """The batched backend's episodes of the case (cached: the unchanged specs serve many cases)."""
    key = f"{env_id} {kwargs!r}"
    if key not in _BATCHED:
        spec = EnvSpec(env_id, kwargs, max_episode_steps=KWARG_STEPS)
        policy, params = population(spec, KWARG_MEMBERS, sigma=0.3)
        _BATCHED[key] = _episodes(MujocoBatchBackend(spec, policy, nthread=1, workers=1).rollout(params, KWARG_SEEDS))
    return _BATCHED[key]


@pytest.mark.parametrize("env_id, kwargs, outcome", KWARG_CASES, ids=[_case_id(case) for case in KWARG_CASES])
def test_keyword_arguments_are_reproduced_bit_for_bit_or_refused_by_name(env_id, kwargs, outcome):
    spec = EnvSpec(env_id, kwargs, max_episode_steps=KWARG_STEPS)
    keyword = next(iter(kwargs))
    reason = MujocoBatchBackend.refusal(spec)
    if outcome == REFUSED:
        assert reason is not None and f"env.kwargs.{keyword}=" in reason, reason
        with pytest.raises(ValueError, match=f"env.kwargs.{keyword}="):
            MujocoBatchBackend(spec, population(env_id, 1, sigma=0.0)[0], nthread=1, workers=1)
        return
    assert reason is None
    policy, params = population(spec, KWARG_MEMBERS, sigma=0.3)
    reference = _episodes(GymBackend(spec, policy).rollout(params, KWARG_SEEDS))
    batched = _batched_episodes(env_id, kwargs)
    for key in reference:
        assert batched[key].shape == reference[key].shape and torch.equal(batched[key], reference[key]), key
    without = _batched_episodes(env_id, {k: v for k, v in kwargs.items() if k != keyword})
    assert _equal(batched, without) == (outcome == SAME)


def test_keyword_table_covers_every_constructor_keyword():
    """Every keyword of the five constructors and of MujocoEnv is in the backend's documented sets;
    each task's own keywords have a line for that task, the rendering ones and xml_file a line."""
    import inspect

    from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

    rendering = set(inspect.signature(MujocoEnv.__init__).parameters) - {"self", "model_path", "frame_skip", "observation_space"}
    assert rendering == RENDERING_KWARGS
    shared = RENDERING_KWARGS | {"xml_file"}
    for env_id in ENV_IDS:
        own = set(constructor_keywords(env_id)) - {"kwargs"}
        assert own <= REPRODUCED_KWARGS | RENDERING_KWARGS, env_id
        tested = {key for task, kwargs, _ in KWARG_CASES if task == env_id for key in kwargs}
        assert own - shared <= tested, (env_id, own - shared - tested)
    assert shared <= {key for _, kwargs, _ in KWARG_CASES for key in kwargs}
