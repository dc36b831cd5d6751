"""benchmarks.es_population's replay ceiling steps the very episodes the evaluation played."""
from __future__ import annotations

import numpy as np
import pytest

from benchmarks.es_population import make_population, replay
from torchrl_esrl.collectors.mujoco_batch import MujocoBatchBackend
from torchrl_esrl.modules.population import PopulationActor


@pytest.mark.parametrize("env_id", ["Walker2d-v5", "Ant-v5"])
def test_replay_ends_each_member_where_its_episode_ended(env_id):
    members, steps = 8, 60
    actor, params, mirrored = make_population(env_id, members, sigma=0.5)
    seeds = list(range(100, 100 + members))
    backend = MujocoBatchBackend(env_id, PopulationActor(actor), max_episode_steps=steps, nthread=2)
    played = backend.rollout(params, seeds, mirrored)
    batch, seconds, _ = replay(env_id, played, seeds, nthread=2)
    assert seconds > 0
    last = np.cumsum(played.lengths.numpy()) - 1
    final = played.transitions.get(("next", "observation")).numpy()[last]
    positions = batch.bind("qpos")[:, backend.skipped_qpos :]
    assert np.array_equal(final[:, : positions.shape[1]], positions.astype(np.float32))  # bit for bit
    if env_id == "Walker2d-v5":
        assert (played.lengths < steps).any()  # members stopped at their own steps
