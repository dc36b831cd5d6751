"""Every use of a TorchRL (or tensordict) private attribute in this project, fenced in one place.

TorchRL's public API does not cover a few things this project needs (the reasons are given per
function). Each access goes through a function here, so a TorchRL upgrade that renames one breaks
this module only, and ``tests/test_torchrl_private.py`` fails loudly naming what changed.
Nothing outside this module may touch a name starting with ``_`` on a TorchRL object.

``PRIVATE_NAMES`` lists, per TorchRL class, the private names used here; the test builds a real
object of each class and checks that every name is still there.
"""
from __future__ import annotations

from tensordict import TensorDictBase
from torchrl.data import TensorStorage

PRIVATE_NAMES: dict[str, tuple[str, ...]] = {
    "torchrl.data.LazyTensorStorage": ("_storage",),
    "torchrl.objectives.TD3Loss": ("_maybe_get_priority_weight", "_cached_detach_qvalue_network_params", "_reduce_loss"),
    "torchrl.objectives.SoftUpdate": ("_target_names", "_sources", "_targets"),
    "torchrl.collectors.Collector": ("_carrier", "_frames", "_iter", "_traj_pool"),
    "torchrl.envs.GymEnv": ("_env",),
}

# ------------------------------------------------------------------------ data (replay buffers)


def tensor_storage_data(storage) -> TensorDictBase | None:
    """The TensorDict a TorchRL ``TensorStorage`` (``LazyTensorStorage``...) writes into; None
    before its first write (or for a storage of plain tensors / pytrees).

    Why private: the MultiBuffer gathers a batch from three storages straight into one
    preallocated TensorDict (one ``index_select`` per key and buffer). The public
    ``storage.get(index)`` builds a new TensorDict per call (after slicing ``[:len]`` when the
    storage is not full), and three of those plus a ``torch.cat`` cost about 2.5x one buffer's
    ``sample`` (``benchmarks/buffer_sampling.py``, "naive"). No public accessor returns the
    storage's tensors themselves.
    """
    if not isinstance(storage, TensorStorage) or not storage.initialized:
        return None
    data = storage._storage
    return data if isinstance(data, TensorDictBase) else None


# ---------------------------------------------------------------------- objectives (TD3 loss)
# Used by a TD3Loss subclass whose actor loss runs one critic instead of TorchRL's two; it
# re-implements ``TD3Loss.actor_loss`` with TD3Loss's own helpers, which are private.


def loss_priority_weight(loss, tensordict):
    """``LossModule._maybe_get_priority_weight``: the importance weights of a prioritized batch
    (None otherwise). Private: no public accessor; a subclass overriding ``actor_loss`` must
    weigh its loss exactly as TorchRL does."""
    return loss._maybe_get_priority_weight(tensordict)


def loss_detached_qvalue_params(loss):
    """``TD3Loss._cached_detach_qvalue_network_params``: the critics' parameters detached from the
    graph (the actor loss must not train the critics). Private: TorchRL builds and caches this
    TensorDict internally; rebuilding it per call costs a detach of every parameter per update."""
    return loss._cached_detach_qvalue_network_params


def reduce_loss(loss, value, tensordict, weights):
    """``LossModule._reduce_loss``: the loss's ``reduction`` ("mean"...) with priority weights.
    Private: the public ``loss.reduction`` names the reduction but TorchRL applies it (and the
    weights) only through this method."""
    return loss._reduce_loss(value, tensordict=tensordict, weights=weights)


def soft_update_pairs(updater) -> tuple[list, list]:
    """Source and target tensors of a TorchRL ``SoftUpdate`` (``target.lerp_(source, 1 - eps)``),
    as two aligned lists, for one ``torch._foreach_lerp_`` over all of them.

    Private: ``SoftUpdate`` keeps them in ``_sources``/``_targets`` (filled lazily, hence the
    ``getattr`` over ``_target_names`` first) and offers only a per-tensor ``step()``.
    """
    for name in updater._target_names:
        getattr(updater.loss_module, name)
    sources, targets = [], []
    for key, param in updater._sources.items():
        target = updater._targets.get(f"target_{key}")
        if target.requires_grad:
            raise RuntimeError("the target parameter is part of a graph.")
        if isinstance(param, TensorDictBase):  # the loss's stacked parameter TensorDicts
            for leaf in param.keys(True, True):
                sources.append(param.get(leaf).data)
                targets.append(target.get(leaf).data)
        else:
            sources.append(param.data)
            targets.append(target.data)
    return sources, targets


# ------------------------------------------------------------------ collectors (TD3 env state)
# A checkpoint taken mid-episode restores the collector's carried tensordict (the observation it
# acts on next, RewardSum's and StepCounter's running values) and the gymnasium simulator.
# ``Collector.state_dict`` saves frames/iter/trajectory pool but not the carrier, and its
# ``load_state_dict`` starts a fresh trajectory (a new trajectory id) instead of continuing one.


def collector_carrier(collector) -> TensorDictBase:
    """The tensordict a ``Collector`` carries between steps (``_carrier``). Private: no accessor."""
    return collector._carrier


def set_collector_carrier(collector, carrier: TensorDictBase) -> None:
    """Replace the carried tensordict (restore mid-episode). Private: no setter."""
    collector._carrier = carrier


def collector_counters(collector) -> tuple[int, int]:
    """``(frames, iter)`` of a ``Collector``. Public read: ``collector.state_dict()`` (which also
    copies the env transforms' and policy's state); this reads the two counters alone."""
    return int(collector._frames), int(collector._iter)


def set_collector_counters(collector, frames: int, iteration: int) -> None:
    """Set ``(frames, iter)``. Private: the public ``load_state_dict`` also allocates a new
    trajectory id and needs the env's full state dict."""
    collector._frames, collector._iter = int(frames), int(iteration)


def collector_traj_pool(collector):
    """The ``Collector``'s trajectory-id pool (``state_dict``/``load_state_dict``). Private: only
    reachable through ``Collector.load_state_dict``, which also resets the carrier's ids."""
    return collector._traj_pool


def gym_env_of(env):
    """The gymnasium env inside a TorchRL ``GymEnv``/``GymWrapper`` (under any TransformedEnv):
    for its simulator state (MuJoCo ``mj_getState``, ``np_random``, wrapper counters). Private:
    ``GymWrapper`` keeps it in ``_env`` and has no public accessor."""
    while not hasattr(env, "_env"):
        env = env.base_env
    return env._env
