"""Every use of a private attribute of TorchRL, tensordict, torch (or gymnasium) in this project, fenced in one place.

TorchRL's public API does not cover a few things this project needs (the reasons are given per
function). Each access goes through a function here, so a TorchRL upgrade that renames one breaks
this module only, and ``tests/test_torchrl_private.py`` fails loudly naming what changed.
Nothing outside this module may touch a name starting with ``_`` on a TorchRL object.

``PRIVATE_NAMES`` lists, per TorchRL class, the private names used here; the test builds a real
object of each class and checks that every name is still there.
"""
from __future__ import annotations

import functools
import weakref

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import (
    LazyTensorStorage,
    RandomSampler,
    TensorDictReplayBuffer,
    TensorDictRoundRobinWriter,
    TensorStorage,
)

from torchrl_esrl.arrays import numpy_views

PRIVATE_NAMES: dict[str, tuple[str, ...]] = {
    "torchrl.data.LazyTensorStorage": ("_storage", "_len", "_set_last_cursor", "_last_cursor", "_bump_mutation_revision"),
    "torchrl.data.TensorDictRoundRobinWriter": ("_cursor", "_write_count", "_track_generations", "_mark_update_entities"),
    "torchrl.objectives.TD3Loss": ("_maybe_get_priority_weight", "_loss_mask_keys", "_cached_detach_qvalue_network_params", "_reduce_loss", "_make_vmap", "_AcceptedKeys"),
    "torchrl.objectives.SoftUpdate": ("_target_names", "_sources", "_targets"),
    "torchrl.collectors.Collector": ("_carrier", "_frames", "_iter", "_traj_pool"),
    "torchrl.envs.GymEnv": ("_env",),
    "tensordict.TensorDict": ("_new_unsafe", "_tensordict"),
    "torch": ("_foreach_lerp_", "_foreach_add_", "_fused_adam_"),
}

# ------------------------------------------------------------------------ data (replay buffers)


def unchecked_tensordict(source: dict, batch_size: torch.Size, device) -> TensorDictBase:
    """``TensorDict(source, batch_size=batch_size, device=device)`` without its checks of every
    leaf (nested dicts become nested TensorDicts, as the constructor makes them). Only for
    leaves built to fit: CPU tensors on ``device`` whose leading dims are ``batch_size``.

    Why private: the TD3 collector builds one 8-leaf TensorDict per frame, and the public
    constructor validates every leaf again; ``TensorDict._new_unsafe`` is tensordict's own
    constructor for data it already knows to be valid (docs/performance.md, "buffer_writes").
    ``tests/test_torchrl_private.py`` checks it against the public constructor.
    """
    return TensorDict._new_unsafe(source, batch_size=batch_size, device=device)


def tensordict_leaves(data: TensorDictBase, keys) -> list:
    """``[data.get(key) for key in keys]``, read from the leaf dicts of a plain ``TensorDict``
    (``get`` itself for other TensorDict types, or where a key does not lead to a tensor).

    Why private: the TD3 side writes one 7-key transition per frame, and ``get`` of a nested key
    goes through tensordict's key handling each time; ``TensorDict._tensordict`` is the dict
    ``get`` reads from. ``tests/test_torchrl_private.py`` checks it against ``get``.
    """
    leaves = []
    for key in keys:
        node = data
        for name in (key,) if isinstance(key, str) else key:
            node = node._tensordict.get(name) if type(node) is TensorDict else None
        leaves.append(node if isinstance(node, torch.Tensor) else data.get(key))
    return leaves


def tensor_storage_data(storage) -> TensorDictBase | None:
    """The TensorDict a TorchRL ``TensorStorage`` (``LazyTensorStorage``...) writes into; None
    before its first write (or for a storage of plain tensors / pytrees).

    Why private: the MultiBuffer gathers a batch from three storages straight into one
    preallocated TensorDict (one ``index_select`` per key and buffer). The public
    ``storage.get(index)`` builds a new TensorDict per call (after slicing ``[:len]`` when the
    storage is not full), then the parts are concatenated (``benchmarks/buffer_sampling.py``,
    "naive"). No public accessor returns the storage's tensors themselves.
    """
    if not isinstance(storage, TensorStorage) or not storage.initialized:
        return None
    data = storage._storage
    return data if isinstance(data, TensorDictBase) else None


_APPEND_LAYOUTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # buffer -> (storage TensorDict, keys, their leaves, index leaf, numpy views of those leaves, leaf dtypes and item shapes)


def append_rows(buffer, data: TensorDictBase, keys=None) -> torch.Tensor | None:
    """Write the flat batch ``data`` into ``buffer`` exactly as ``buffer.extend(data)`` does (same
    rows at the same indices, the stored ``"index"`` leaf, the writer's cursor and count, the
    storage's length), one tensor copy per key; None, writing nothing, when the buffer is not
    the plain layout this covers (the caller then calls ``extend``). ``keys``: the keys to store,
    as ``extend(data.select(*keys))`` would (``data`` may hold more); all of ``data``'s otherwise.

    Why private: the TD3 side writes one transition per frame, and ``TensorDictReplayBuffer.extend``
    runs its TensorDict machinery (inverse transform, ``to``, validation of every leaf) on each
    (``benchmarks/td3_frame.py``, docs/performance.md). The
    writer's cursor and the storage's length have no public setters. ``tests/test_torchrl_private.py``
    compares this path with ``extend`` on a wrapping buffer: contents, length, cursor, state dicts.
    """
    storage, writer = buffer.storage, buffer.writer
    if (
        type(buffer) is not TensorDictReplayBuffer
        or type(storage) is not LazyTensorStorage
        or type(writer) is not TensorDictRoundRobinWriter
        or type(buffer.sampler) is not RandomSampler
        or writer._track_generations
        or (buffer.transform is not None and len(buffer.transform))
        or buffer.dim_extend != 0
        or not storage.initialized
        or data.batch_dims != 1
        or data.device not in (None, storage.device)
    ):
        return None
    stored = storage._storage
    keys = tuple(data.keys(True, True)) if keys is None else tuple(keys)
    layout = _APPEND_LAYOUTS.get(buffer)
    if layout is None or layout[0] is not stored or layout[1] != keys:
        if not isinstance(stored, TensorDictBase) or sorted(map(str, [*keys, "index"])) != sorted(map(str, stored.keys(True, True))):
            return None
        destinations, index_leaf = [stored.get(key) for key in keys], stored.get("index")
        # numpy views of CPU storage: a one-row slice copy through numpy skips torch's
        # __setitem__ dispatch (the TD3 side writes one row per frame).
        arrays = numpy_views([*destinations, index_leaf])
        kinds = [(d.dtype, d.shape[1:]) for d in destinations]
        layout = _APPEND_LAYOUTS[buffer] = (stored, keys, destinations, index_leaf, arrays, kinds)
    _, _, destinations, stored_index, arrays, kinds = layout
    values = tensordict_leaves(data, keys)
    if any(v.dtype != dtype or v.shape[1:] != shape for v, (dtype, shape) in zip(values, kinds)):
        return None  # extend casts (or refuses) as TorchRL decides
    rows, capacity = data.batch_size[0], storage.max_size
    cursor = writer._cursor
    index = torch.from_numpy(np.arange(cursor, cursor + rows, dtype=np.int64))  # torch.arange's values, without its dispatch
    sources = numpy_views(values) if cursor + rows <= capacity and arrays is not None else None
    writer._cursor = (cursor + rows) % capacity
    writer._write_count += rows
    if sources is not None:  # rows that fit before the end of the storage: one slice, copied through numpy
        for source, array in zip(sources, arrays):
            array[cursor : cursor + rows] = source
        arrays[-1][cursor : cursor + rows] = index.numpy()
    else:  # a wrap (it needs the indices), or storage numpy cannot view: torch's copies
        where = slice(cursor, cursor + rows) if cursor + rows <= capacity else index.remainder_(capacity)
        for value, destination in zip(values, destinations):
            destination[where] = value
        stored_index[where] = index
    # What _set_last_cursor(index) records (the index, and its last entry as the shared int),
    # without its tensor reshape, indexing and item.
    storage._set_last_cursor((cursor + rows - 1) % capacity)
    storage._last_cursor = index
    storage._len = min(storage._len + rows, capacity)
    storage._bump_mutation_revision()
    writer._mark_update_entities(index)
    buffer.sampler.extend(index)
    return index


# ---------------------------------------------------------------------- objectives (TD3 loss)
def loss_priority_weight(loss, tensordict):
    """The importance weights a TorchRL loss applies to ``tensordict`` (None without prioritised
    sampling). Used by the TD3 loss overrides to fall back to TorchRL's own code when weights
    are present; the public API has no getter (``LossModule._maybe_get_priority_weight``)."""
    return loss._maybe_get_priority_weight(tensordict)


def reweights_or_masks(loss, tensordict) -> bool:
    """Whether a TorchRL loss's reduction would weight (prioritised replay) or mask (its loss-mask
    keys, e.g. ``("collector", "mask")``) this batch. The hand-written TD3 gradients compute the
    plain batch mean only and hand such batches to TorchRL's own code; the public API has no
    getter for either (``LossModule._maybe_get_priority_weight``, ``LossModule._loss_mask_keys``)."""
    top = tensordict.keys()
    if loss.use_prioritized_weights in (True, "auto"):
        key = loss.tensor_keys.priority_weight
        if key in top if isinstance(key, str) else loss._maybe_get_priority_weight(tensordict) is not None:
            return True  # _maybe_get_priority_weight's weights (its own call, and its error, for a nested key)
    return any(has_entry(tensordict, key, top) for key in loss._loss_mask_keys())


def has_entry(tensordict, key, top=None) -> bool:
    """``key in tensordict.keys(True)`` for a nested key (a string or a tuple), the first level
    looked up alone first (``top``: ``tensordict.keys()``, where the caller has it): a batch lacks
    most keys a loss looks for, and the nested view walks the whole tensordict to say so."""
    if top is None:
        top = tensordict.keys()
    if isinstance(key, str):
        return key in top
    if len(key) == 1 or key[0] not in top:
        return len(key) == 1 and key[0] in top
    return key in tensordict.keys(True)


def reduce_loss(loss, value, tensordict, weights):
    """A TorchRL loss's reduction (``reduction`` and priority weights) of a per-sample loss;
    ``LossModule._reduce_loss`` has no public counterpart and the Q1-only actor loss must reduce
    exactly as ``TD3Loss.actor_loss`` does."""
    return loss._reduce_loss(value, tensordict=tensordict, weights=weights)


def soft_update_tensors(updater) -> tuple[list, list]:
    """(source, target) tensor lists of a ``SoftUpdate``, in the order ``SoftUpdate.step`` visits
    them. ``SoftUpdate`` keeps them in ``_sources``/``_targets`` (filled lazily by looking the
    names up on the loss) with no public accessor; one foreach call over them replaces its loop."""
    for name in updater._target_names:
        getattr(updater.loss_module, name)
    sources, targets = [], []
    for key, param in updater._sources.items():
        target = updater._targets.get(f"target_{key}")
        if target.requires_grad:
            raise RuntimeError("the target parameter is part of a graph.")
        if hasattr(param, "keys"):  # the loss's stacked parameter TensorDicts
            for leaf in param.keys(True, True):
                sources.append(param.get(leaf).data)
                targets.append(target.get(leaf).data)
        else:
            sources.append(param.data)
            targets.append(target.data)
    return sources, targets


def fused_adam_step(optimizer: torch.optim.Adam) -> None:
    """``optimizer.step()`` of a fused (``fused=True``) torch Adam, as one call of the kernel it
    runs (``torch._fused_adam_``) after the same step-count increment (``torch._foreach_add_``).

    ``Optimizer.step`` runs Python around that kernel (hooks, state lookups, option checks) on
    every call (docs/performance.md, "adam"). The state tensors are torch's own (``state_dict``
    and checkpoints unchanged); the lists of them are rebuilt whenever the parameters' step
    tensors are not the ones they hold (``load_state_dict`` and ``state.clear()`` replace them).
    Anything but one parameter group of plain fused Adam with every gradient present and no step
    hooks goes through ``optimizer.step()``, which also makes the first step (it creates the
    state). ``tests/test_torchrl_private.py`` checks parameters and state against
    ``optimizer.step()`` bit for bit, across a ``load_state_dict`` and a ``state.clear()``.
    """
    group = optimizer.param_groups[0] if len(optimizer.param_groups) == 1 else {}
    params = group.get("params", ())
    direct = (
        group.get("fused") and not group["amsgrad"] and not group["maximize"] and not group["capturable"]
        and not group["differentiable"] and not group.get("decoupled_weight_decay") and not isinstance(group["lr"], torch.Tensor)
        and all(p.grad is not None and p in optimizer.state for p in params)
        and not optimizer_step_hooks(optimizer)
    )
    if not direct:
        optimizer.step()
        return
    steps = [optimizer.state[p]["step"] for p in params]
    cache = optimizer.__dict__.get("_fused_adam_lists")
    if cache is None or len(cache[2]) != len(steps) or any(held is not step for held, step in zip(cache[2], steps)):
        states = [optimizer.state[p] for p in params]
        cache = optimizer.__dict__["_fused_adam_lists"] = ([s["exp_avg"] for s in states], [s["exp_avg_sq"] for s in states], steps)
    exp_avgs, exp_avg_sqs, steps = cache
    beta1, beta2 = group["betas"]
    torch._foreach_add_(steps, 1)
    torch._fused_adam_(
        params, [p.grad for p in params], exp_avgs, exp_avg_sqs, [], steps,
        lr=group["lr"], beta1=beta1, beta2=beta2, weight_decay=group["weight_decay"], eps=group["eps"],
        amsgrad=False, maximize=False, grad_scale=None, found_inf=None,
    )


# TD3Loss / LossModule members that TD3Loss.value_loss and actor_loss call and the hand-written
# TD3 forwards do not.
TD3_LOSS_INTERNALS = ("_maybe_get_priority_weight", "_loss_mask_keys", "_reduce_loss", "_make_vmap", "_cached_detach_qvalue_network_params", "value_estimator")


def overridden_td3_loss_internals(cls: type, base: type) -> list[str]:
    """The members of :data:`TD3_LOSS_INTERNALS` that the loss class ``cls`` overrides relative to
    ``base``: the hand-written TD3 losses skip those calls, so such a subclass gets TD3Loss's code."""
    return [name for name in TD3_LOSS_INTERNALS if getattr(cls, name) is not getattr(base, name)]


@functools.cache
def td3_loss_default_keys():
    """``TD3Loss``'s default tensor keys (``TD3Loss._AcceptedKeys()``, the dataclass its ``tensor_keys``
    is an instance of; no public constructor of the defaults)."""
    from torchrl.objectives import TD3Loss

    return TD3Loss._AcceptedKeys()


def optimizer_step_hooks(optimizer: torch.optim.Optimizer) -> bool:
    """Whether ``optimizer.step()`` would run step hooks (``register_step_pre_hook`` and
    ``register_step_post_hook``, the optimizer's own or global): :func:`fused_adam_step` then calls
    ``step()``. torch keeps them in private dicts with no public getter."""
    from torch.optim import optimizer as torch_optimizer

    return bool(
        optimizer._optimizer_step_pre_hooks or optimizer._optimizer_step_post_hooks
        or torch_optimizer._global_optimizer_pre_hooks or torch_optimizer._global_optimizer_post_hooks
    )


MODULE_HOOK_KINDS = ("forward", "forward_pre", "backward", "backward_pre")  # what torch calls around a module's forward
FORWARD_HOOK_KINDS = MODULE_HOOK_KINDS[:2]  # the kinds that run in a forward without gradient


def module_hook_dicts(modules, kinds: tuple[str, ...] = MODULE_HOOK_KINDS) -> tuple:
    """The dicts in which ``modules`` keep their hooks of ``kinds``, for :func:`module_hooks`
    (torch registers a hook into these same dicts, in place)."""
    return tuple(getattr(m, f"_{kind}_hooks") for m in modules for kind in kinds)


def module_hooks(hook_dicts: tuple, kinds: tuple[str, ...] = MODULE_HOOK_KINDS) -> bool:
    """Whether calling the modules of ``hook_dicts`` (:func:`module_hook_dicts`) would run hooks of
    ``kinds`` (default: forward and backward), a module's own or torch's global ones. The
    hand-written forwards do not call the modules and hand such networks to their references;
    torch keeps the hooks in private dicts with no public getter."""
    return global_module_hooks(kinds) or any(hook_dicts)


def global_module_hooks(kinds: tuple[str, ...] = MODULE_HOOK_KINDS) -> bool:
    """Whether torch's global module hooks of ``kinds`` are registered
    (``torch.nn.modules.module.register_module_forward_hook`` and the like): every module call runs them."""
    from torch.nn.modules import module as torch_module

    return any(getattr(torch_module, f"_global_{kind}_hooks") for kind in kinds)


def gradient_hooks(tensor: torch.Tensor) -> bool:
    """Whether hooks watch ``tensor``'s gradient (``register_hook``, ``register_post_accumulate_grad_hook``):
    the direct backward of the hand-written TD3 losses then leaves it to the autograd engine. torch
    keeps them in private attributes with no public getter."""
    return bool(tensor._backward_hooks) or bool(getattr(tensor, "_post_accumulate_grad_hooks", None))


def function_apply(function: type, *args):
    """``function.apply(*args)`` for a ``torch.autograd.Function`` without ``setup_context``: outside
    functorch transforms, ``Function.apply`` unwraps dead functorch wrappers, then calls the C
    ``_FunctionBase.apply``; this does the same without the Python frame between (``super().apply`` of
    a class method has no public name). Inside a transform it is ``function.apply``."""
    if torch._C._are_functorch_transforms_active():
        return function.apply(*args)
    return _C_FUNCTION_APPLY.__get__(None, function)(*(torch._C._functorch.unwrap_if_dead(a) if isinstance(a, torch.Tensor) else a for a in args))


_C_FUNCTION_APPLY = torch._C._FunctionBase.__dict__["apply"]


def backward_node_class(function: type) -> type:
    """The class of the graph nodes a ``torch.autograd.Function`` subclass creates (``Function._backward_cls``,
    made by its metaclass; no public name)."""
    return function._backward_cls


def without_loss_contexts(loss_class: type, *names: str) -> None:
    """Give ``loss_class`` its own ``names`` methods without the wrapper TorchRL's loss metaclass
    (``_LossMeta``) puts around every public ``*loss`` method: ``set_exploration_type`` and
    ``set_recurrent_mode`` contexts entered and left on each call. They steer the modules a loss
    calls; the hand-written TD3 losses call none (where they hand over, ``TD3Loss``'s own wrapped
    methods run), and the two contexts cost about as much as a small network's forward."""
    for name in names:
        method = loss_class.__dict__[name]
        setattr(loss_class, name, getattr(method, "__wrapped__", method))


def detached_qvalue_params(loss):
    """A TD3 loss's critic parameters, detached and cached per step (``TD3Loss`` builds them for
    its actor loss; there is no public accessor, and detaching again each step costs time)."""
    return loss._cached_detach_qvalue_network_params


# ------------------------------------------------------------------ collectors (TD3 env)
def gym_env_of(env):
    """The gymnasium env inside a TorchRL ``GymEnv``, possibly under ``TransformedEnv`` layers.
    ``GymEnv`` keeps it as ``_env`` with no public accessor; the fast TD3 stepping path and the
    TD3 checkpoint state need the very object TorchRL seeded."""
    while not hasattr(env, "_env"):
        env = env.base_env
    return env._env


def collector_carrier(collector):
    """The TensorDict a TorchRL ``Collector`` carries between batches (the next step's input).
    ``Collector.state_dict`` leaves it out; a checkpoint taken mid-episode needs it."""
    return collector._carrier


def restore_collector(collector, frames: int, iterations: int, carrier, traj_pool_state=None) -> None:
    """Put a TorchRL ``Collector`` back where a checkpoint left it: its counters, carried
    TensorDict and trajectory-id pool (``Collector.load_state_dict`` restores neither the
    carrier nor, for a single env, the counters)."""
    collector._frames, collector._iter = int(frames), int(iterations)
    if traj_pool_state is not None:
        collector._traj_pool.load_state_dict(traj_pool_state)
    collector._carrier = carrier


# ------------------------------------------------------------------ collectors (TD3 env state)
_SCALARS = (bool, int, float, str, type(None))


def _gym_layers(gym_env):
    layers = [gym_env]
    while hasattr(layers[-1], "env"):
        layers.append(layers[-1].env)
    return layers


def gym_env_state(gym_env) -> dict:
    """A gymnasium env's state mid-episode: each wrapper's scalar attributes (``TimeLimit``'s
    ``_elapsed_steps``, ``OrderEnforcing``'s ``_has_reset``...), the core env's ``np_random`` and
    arrays, and for MuJoCo envs the full integration state from ``mj_getState``.

    Why private: gymnasium wrappers keep their episode state in private attributes with no
    getter or setter, and TorchRL's ``GymEnv``/``Collector`` state dicts leave the simulator out;
    a checkpoint taken mid-episode must resume the very episode. Every scalar attribute is copied
    (not a list of names), so a renamed attribute is still saved and restored;
    ``tests/test_td3.py`` resumes a collector mid-episode and compares the frames."""
    layers = _gym_layers(gym_env)
    core = layers[-1]
    state = {
        "wrappers": [{k: v for k, v in vars(w).items() if isinstance(v, _SCALARS) and k != "_saved_kwargs"} for w in layers[:-1]],
        "core": {k: v.copy() if isinstance(v, np.ndarray) else v for k, v in vars(core).items() if isinstance(v, (np.ndarray, *_SCALARS)) and not k.startswith("_ezpickle")},
        "np_random": core.np_random.bit_generator.state,
    }
    if hasattr(core, "model") and hasattr(core, "data"):
        import mujoco

        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        physics = np.empty(mujoco.mj_stateSize(core.model, spec))
        mujoco.mj_getState(core.model, core.data, physics, spec)
        state["mujoco"] = physics
    return state


def load_gym_env_state(gym_env, state: dict) -> None:
    """Restore :func:`gym_env_state`'s snapshot into ``gym_env`` (its wrappers and core env)."""
    layers = _gym_layers(gym_env)
    for layer, attributes in zip(layers[:-1], state["wrappers"]):
        vars(layer).update(attributes)
    core = layers[-1]
    vars(core).update(state["core"])
    core.np_random.bit_generator.state = state["np_random"]
    if "mujoco" in state:
        import mujoco

        mujoco.mj_setState(core.model, core.data, np.asarray(state["mujoco"], dtype=np.float64), mujoco.mjtState.mjSTATE_INTEGRATION)


# ------------------------------------------------------------- gymnasium MuJoCo task constants
GYM_MUJOCO_CONSTANTS = (
    "_forward_reward_weight", "_ctrl_cost_weight", "_healthy_reward", "_terminate_when_unhealthy",
    "_healthy_z_range", "_healthy_angle_range", "_healthy_state_range", "_contact_cost_weight",
    "_contact_force_range", "_main_body", "_exclude_current_positions_from_observation",
    "_include_cfrc_ext_in_observation",
)  # fmt: skip


def gym_mujoco_constants(env) -> dict:
    """The reward and termination constants of a gymnasium v5 MuJoCo env (those of
    :data:`GYM_MUJOCO_CONSTANTS` it has), as its ``step`` reads them.

    Why private: gymnasium keeps its constructor arguments in private attributes only; the
    batched ES backend recomputes rewards from them so that it cannot drift from gymnasium's
    values. ``tests/test_torchrl_private.py`` checks, per task, that every constant the task's
    rules read is still there; ``tests/test_mujoco_batch.py`` compares the rewards."""
    return {k: getattr(env, k) for k in GYM_MUJOCO_CONSTANTS if hasattr(env, k)}


# ----------------------------------------------------------------------------------- torch ops
def foreach_lerp_(targets: list, sources: list, weight: float) -> None:
    """``target.lerp_(source, weight)`` for every pair, as one call.

    Why private: ``torch._foreach_lerp_`` is the multi-tensor kernel torch's own optimisers use;
    torch has no public foreach API. ``tests/test_torchrl_private.py`` compares it with
    ``lerp_`` tensor by tensor."""
    torch._foreach_lerp_(targets, sources, weight)
