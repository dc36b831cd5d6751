"""What one population evaluation produces (paper, Algorithm 2 "Evaluate"): per-member returns and
lengths, and all *real* transitions in TorchRL's layout::

    observation, action,
    next/{observation, reward, done, terminated, truncated},
    episode_return,            # the return of the episode the transition belongs to
    collector/traj_ids         # the member (offspring) index

Members whose episode ends early contribute only the steps they took.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDict


@dataclass
class Generation:
    """What one population evaluation produced."""

    returns: torch.Tensor  # [P] float64, undiscounted episode returns (the fitness)
    lengths: torch.Tensor  # [P] int64, steps of each episode
    transitions: TensorDict  # [sum(lengths)] flat, member-major, time-ordered within a member

    @property
    def frames(self) -> int:
        return int(self.lengths.sum())

    def member_mask(self, members: torch.Tensor) -> torch.Tensor:
        """Transition mask selecting the members where ``members[P]`` (bool) is True."""
        return members[self.transitions.get(("collector", "traj_ids"))]

    def members(self, start: int, stop: int) -> Generation:
        """Members ``start..stop-1`` as a Generation of their own (member indices from 0)."""
        ends = torch.cumsum(self.lengths, 0)
        first, last = (int(ends[start - 1]) if start else 0), (int(ends[stop - 1]) if stop else 0)
        transitions = self.transitions[first:last]
        transitions.set(("collector", "traj_ids"), transitions.get(("collector", "traj_ids")) - start)
        return Generation(self.returns[start:stop], self.lengths[start:stop], transitions)


def transitions_from_arrays(obs, actions, next_obs, rewards, terminated, truncated, lengths, returns) -> TensorDict:
    """Flatten padded ``[P, T, ...]`` numpy arrays into the TorchRL transition layout (real steps only).

    One gather of the real rows per array (member ``p``'s steps ``0..lengths[p]-1``, member after
    member): the work grows with the steps played, not with the padded horizon."""
    lengths = np.asarray(lengths, dtype=np.int64)
    members = np.repeat(np.arange(len(lengths)), lengths)
    steps = np.arange(len(members)) - np.repeat(np.cumsum(lengths) - lengths, lengths)

    def take(array, dtype):
        return torch.from_numpy(np.asarray(array)[members, steps].astype(dtype, copy=False))

    reward = take(rewards, np.float32).unsqueeze(-1)
    term = take(terminated, np.bool_).unsqueeze(-1)
    trunc = take(truncated, np.bool_).unsqueeze(-1)
    members_t = torch.from_numpy(members)
    return TensorDict(
        {
            "observation": take(obs, np.float32),
            "action": take(actions, np.float32),
            "next": {
                "observation": take(next_obs, np.float32),
                "reward": reward,
                "done": term | trunc,
                "terminated": term,
                "truncated": trunc,
            },
            "episode_return": torch.as_tensor(returns, dtype=torch.float32)[members_t].unsqueeze(-1),
            "collector": {"traj_ids": members_t},
        },
        batch_size=[len(members)],
    )


def population_returns(returns: torch.Tensor) -> dict:
    """The ``population_mean_return`` and ``population_max_return`` columns of ``metrics.csv`` over
    ``returns``, the members' returns of an iteration's generations ("" where it played none)."""
    if returns.numel() == 0:
        return {"population_mean_return": "", "population_max_return": ""}
    return {"population_mean_return": returns.mean().item(), "population_max_return": returns.max().item()}
