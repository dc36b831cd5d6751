"""A generation's transitions are each member's real steps, member after member."""
from __future__ import annotations

import numpy as np
import torch

from torchrl_esrl.collectors.generation import transitions_from_arrays


def test_transitions_are_each_members_first_steps_in_order():
    rng = np.random.default_rng(0)
    population, horizon, obs_dim, act_dim = 5, 9, 3, 2
    lengths = np.array([9, 1, 4, 0, 7])
    obs_traj = rng.standard_normal((population, horizon + 1, obs_dim))  # float64, as gymnasium's
    actions = rng.standard_normal((population, horizon, act_dim)).astype(np.float32)
    rewards = rng.standard_normal((population, horizon))
    terminated, truncated = rng.random((population, horizon)) < 0.3, rng.random((population, horizon)) < 0.3
    returns = rewards.sum(axis=1)
    td = transitions_from_arrays(obs_traj[:, :-1], actions, obs_traj[:, 1:], rewards, terminated, truncated, lengths, returns)

    def rows(array, next_step=0):  # the reference: member p's steps 0..lengths[p]-1, concatenated
        return torch.as_tensor(np.concatenate([array[p, next_step : next_step + length] for p, length in enumerate(lengths)]))

    assert td.batch_size == torch.Size([lengths.sum()])
    assert torch.equal(td.get("observation"), rows(obs_traj).float())
    assert torch.equal(td.get(("next", "observation")), rows(obs_traj, 1).float())
    assert torch.equal(td.get("action"), rows(actions))
    assert torch.equal(td.get(("next", "reward")), rows(rewards).float().unsqueeze(-1))
    assert torch.equal(td.get(("next", "terminated")), rows(terminated).unsqueeze(-1))
    assert torch.equal(td.get(("next", "truncated")), rows(truncated).unsqueeze(-1))
    assert torch.equal(td.get(("next", "done")), (rows(terminated) | rows(truncated)).unsqueeze(-1))
    members = torch.repeat_interleave(torch.arange(population), torch.as_tensor(lengths))
    assert torch.equal(td.get(("collector", "traj_ids")), members)
    assert td.get(("collector", "traj_ids")).dtype == torch.int64
    assert torch.equal(td.get("episode_return"), torch.as_tensor(returns, dtype=torch.float32)[members].unsqueeze(-1))
