"""Every use of a TorchRL (or tensordict) private attribute in this project, fenced in one place.

TorchRL's public API does not cover a few things this project needs (the reasons are given per
function). Each access goes through a function here, so a TorchRL upgrade that renames one breaks
this module only, and ``tests/test_torchrl_private.py`` fails loudly naming what changed.
Nothing outside this module may touch a name starting with ``_`` on a TorchRL object.
"""
from __future__ import annotations

# ------------------------------------------------------------------------ data (replay buffers)


# ---------------------------------------------------------------------- objectives (TD3 loss)
def loss_priority_weight(loss, tensordict):
    """The importance weights a TorchRL loss applies to ``tensordict`` (None without prioritised
    sampling). Used by the TD3 loss overrides to fall back to TorchRL's own code when weights
    are present; the public API has no getter (``LossModule._maybe_get_priority_weight``)."""
    return loss._maybe_get_priority_weight(tensordict)


def detached_qvalue_params(loss):
    """A TD3 loss's critic parameters, detached and cached per step (``TD3Loss`` builds them for
    its actor loss; there is no public accessor, and detaching again each step costs time)."""
    return loss._cached_detach_qvalue_network_params


# ------------------------------------------------------------------ collectors (TD3 env state)
def gym_env_of(env):
    """The gymnasium env inside a TorchRL ``GymEnv``, possibly under ``TransformedEnv`` layers.
    ``GymEnv`` keeps it as ``_env`` with no public accessor; the fast TD3 stepping path and the
    TD3 checkpoint state need the very object TorchRL seeded."""
    while not hasattr(env, "_env"):
        env = env.base_env
    return env._env
