"""The TorchRL private names ``torchrl_esrl.torchrl_private`` relies on, checked on real objects.

A TorchRL upgrade that renames one fails here first, naming the attribute, the class and the
installed TorchRL version; the accessors are also checked to return what they claim.
"""
import gymnasium
import pytest
import torch
import torchrl
from tensordict import LazyStackedTensorDict, TensorDict
from torchrl.collectors import Collector
from torchrl.data import (
    LazyTensorStorage,
    ListStorage,
    SamplerWithoutReplacement,
    TensorDictReplayBuffer,
)
from torchrl.envs import GymEnv
from torchrl.objectives import SoftUpdate, TD3Loss

from torchrl_esrl import torchrl_private
from torchrl_esrl.envs import make_env
from torchrl_esrl.modules.networks import make_actor, make_critic


@pytest.fixture(scope="module")
def env():
    return make_env("pendulum", seed=0)


@pytest.fixture(scope="module")
def td3_loss(env):
    torch.manual_seed(0)
    actor, critic = make_actor(3, env.action_spec, (16,)), make_critic(3, 1, (16,))
    loss = TD3Loss(actor_network=actor, qvalue_network=critic, action_spec=env.action_spec, num_qvalue_nets=2, delay_actor=True, delay_qvalue=True)
    loss.make_value_estimator(gamma=0.99)
    return loss


@pytest.fixture(scope="module")
def collector(env):
    collector = Collector(env, None, frames_per_batch=10, total_frames=-1)
    next(iter(collector))
    yield collector
    collector.shutdown()


def batch(n=8):
    return TensorDict(
        {"observation": torch.randn(n, 3), "action": torch.rand(n, 1) * 2 - 1,
         "next": {"observation": torch.randn(n, 3), "reward": torch.randn(n, 1), "done": torch.zeros(n, 1, dtype=torch.bool),
                  "terminated": torch.zeros(n, 1, dtype=torch.bool)}},
        batch_size=[n],
    )


def real_objects(env, td3_loss, collector) -> dict:
    storage = LazyTensorStorage(10)
    storage.set(range(2), batch(2))
    return {
        "torchrl.data.LazyTensorStorage": storage,
        "torchrl.data.TensorDictRoundRobinWriter": TensorDictReplayBuffer(storage=LazyTensorStorage(10)).writer,
        "torchrl.objectives.TD3Loss": td3_loss,
        "torchrl.objectives.SoftUpdate": SoftUpdate(td3_loss, tau=0.005),
        "torchrl.collectors.Collector": collector,
        "torchrl.envs.GymEnv": GymEnv("Pendulum-v1"),
        "tensordict.TensorDict": batch(2),
        "torch": torch,
    }


def test_every_private_name_still_exists(env, td3_loss, collector):
    objects = real_objects(env, td3_loss, collector)
    assert set(objects) == set(torchrl_private.PRIVATE_NAMES), "PRIVATE_NAMES and this test list different classes"
    missing = [
        f"{type(objects[cls]).__name__}.{name} (listed for {cls})"
        for cls, names in torchrl_private.PRIVATE_NAMES.items()
        for name in names
        if not hasattr(objects[cls], name)
    ]
    assert not missing, f"TorchRL {torchrl.__version__} / torch {torch.__version__} no longer has {', '.join(missing)}: update torchrl_esrl/torchrl_private.py"


# ---------------------------------------------------------------------------------- data
def test_tensor_storage_data_is_the_storage_itself():
    storage = LazyTensorStorage(10)
    assert torchrl_private.tensor_storage_data(storage) is None  # nothing written yet
    data = batch(4)
    storage.set(range(4), data)
    tensors = torchrl_private.tensor_storage_data(storage)
    assert tensors.batch_size == torch.Size([10])  # the whole preallocated storage
    assert torch.equal(tensors["observation"][:4], data["observation"])
    assert torch.equal(tensors[:4]["next", "reward"], storage.get(slice(0, 4))["next", "reward"])
    tensors["observation"][0] = 7.0  # the same memory, not a copy
    assert (storage.get(torch.tensor([0]))["observation"] == 7).all()
    assert torchrl_private.tensor_storage_data(ListStorage(10)) is None


def test_unchecked_tensordict_is_what_the_constructor_builds():
    leaves = {"observation": torch.randn(3, 2), "next": {"reward": torch.randn(3, 1), "done": torch.zeros(3, 1, dtype=torch.bool)}}
    checked = TensorDict(leaves, batch_size=[3], device="cpu")
    unchecked = torchrl_private.unchecked_tensordict(leaves, torch.Size([3]), torch.device("cpu"))
    assert type(unchecked) is TensorDict and type(unchecked["next"]) is TensorDict
    assert unchecked.batch_size == checked.batch_size and unchecked["next"].batch_size == checked["next"].batch_size
    assert unchecked.device == checked.device and unchecked["next"].device == checked["next"].device
    assert set(unchecked.keys(True, True)) == set(checked.keys(True, True))
    assert all(unchecked.get(key) is checked.get(key) for key in checked.keys(True, True))  # the same tensors, no copies
    assert (unchecked == checked).all()


def test_tensordict_leaves_are_what_get_returns():
    data = TensorDict({"observation": torch.randn(3, 2), "next": {"reward": torch.randn(3, 1), "done": torch.zeros(3, 1, dtype=torch.bool)}}, batch_size=[3])
    keys = ["observation", ("next", "reward"), ("next", "done"), ("observation",)]
    assert all(leaf is data.get(key) for leaf, key in zip(torchrl_private.tensordict_leaves(data, keys), keys))
    stacked = LazyStackedTensorDict.lazy_stack([data[0], data[1]])  # not a plain TensorDict: read through get
    for leaf, key in zip(torchrl_private.tensordict_leaves(stacked, keys), keys):
        assert torch.equal(leaf, stacked.get(key))
    missing = [("next", "missing"), "missing"]  # what get returns for these, too
    assert torchrl_private.tensordict_leaves(data, missing) == [data.get(key) for key in missing]


def test_append_rows_writes_what_extend_writes():
    torch.manual_seed(0)
    stock, fast = (TensorDictReplayBuffer(storage=LazyTensorStorage(25), batch_size=7) for _ in range(2))
    stock.extend(batch(3))  # both initialised by TorchRL's own first write
    fast.extend(stock.storage.get(slice(0, 3)).exclude("index"))
    for step, n in enumerate((1, 1, 5, 1, 12, 1, 9, 1)):  # wraps around the 25-item capacity twice
        data = batch(n)
        expected = stock.extend(data.clone())
        keys = list(data.keys(True, True)) if step % 2 else None  # given by the caller, or read
        index = torchrl_private.append_rows(fast, data.clone(), keys)
        assert torch.equal(index, expected)
        assert len(fast) == len(stock)
        # the last write's cursor, as TorchRL's storage checkpointers and HER read it
        assert torch.equal(fast.storage._last_cursor, stock.storage._last_cursor)
        assert fast.storage._last_cursor_index_value.value == stock.storage._last_cursor_index_value.value
        assert (fast.storage.get(slice(0, len(fast))) == stock.storage.get(slice(0, len(stock)))).all()
    assert fast.writer.state_dict() == stock.writer.state_dict()
    assert fast.storage.state_dict()["_len"] == stock.storage.state_dict()["_len"]
    torch.manual_seed(1)
    sample_stock = stock.sample()
    torch.manual_seed(1)
    assert (fast.sample() == sample_stock).all()


def test_append_rows_declines_what_it_does_not_cover():
    fresh = TensorDictReplayBuffer(storage=LazyTensorStorage(10))
    assert torchrl_private.append_rows(fresh, batch(2)) is None and len(fresh) == 0  # storage not initialised
    fresh.extend(batch(2))
    assert torchrl_private.append_rows(fresh, batch(2).exclude("action")) is None and len(fresh) == 2  # other keys
    as_float64 = batch(2).apply(lambda t: t.double() if t.is_floating_point() else t)
    assert torchrl_private.append_rows(fresh, as_float64) is None and len(fresh) == 2  # another dtype: extend casts
    other_sampler = TensorDictReplayBuffer(storage=LazyTensorStorage(10), sampler=SamplerWithoutReplacement())
    other_sampler.extend(batch(2))
    assert torchrl_private.append_rows(other_sampler, batch(2)) is None and len(other_sampler) == 2


# ----------------------------------------------------------------------------- objectives
def test_td3_loss_helpers(td3_loss):
    data = batch()
    assert torchrl_private.loss_priority_weight(td3_loss, data) is None  # no priorities in the batch
    params = torchrl_private.detached_qvalue_params(td3_loss)
    leaves = list(params.values(True, True))
    assert leaves and not any(p.requires_grad for p in leaves)
    value = torch.randn(8)
    assert torch.allclose(torchrl_private.reduce_loss(td3_loss, value, data, None), value.mean())  # reduction "mean"


@pytest.mark.parametrize("use_weights", [True, False, "auto"])
def test_reweights_or_masks_and_has_entry_say_what_torchrl_would_find(td3_loss, use_weights):
    """reweights_or_masks is TorchRL's own test (``_maybe_get_priority_weight`` or a loss-mask key in
    the nested keys) for batches with and without each entry, a nested priority key included;
    has_entry is ``key in keys(True)``."""
    import copy

    loss = copy.deepcopy(td3_loss)
    loss.use_prioritized_weights = use_weights
    extras = [None, ("priority_weight",), ("collector", "mask"), ("shifted_valid",), ("collector", "other"), ("p", "w")]
    for priority_key in ("priority_weight", ("p", "w")):
        loss.set_keys(priority_weight=priority_key)
        for extra in extras:
            data = batch()
            if extra is not None:
                data.set(extra, torch.ones(8))
            keys = data.keys(True)
            try:
                expected = loss._maybe_get_priority_weight(data) is not None or any(k in keys for k in loss._loss_mask_keys())
            except TypeError:  # TorchRL's own lookup refuses a nested priority key: so does reweights_or_masks
                with pytest.raises(TypeError):
                    torchrl_private.reweights_or_masks(loss, data)
            else:
                assert torchrl_private.reweights_or_masks(loss, data) == expected, (priority_key, extra)
            for key in ("observation", ("observation",), ("next", "reward"), ("next", "x"), ("observation", "x"), "x", ("x", "y"), *filter(None, extras)):
                assert torchrl_private.has_entry(data, key) == (key in keys), key


def test_function_apply_is_function_apply():
    """function_apply gives what Function.apply gives: outputs, the node class, the gradients."""

    class Scale(torch.autograd.Function):
        @staticmethod
        def forward(ctx, factor, x, w):
            ctx.save_for_backward(x, w)
            ctx.factor = factor
            return (x * w).sum() * factor

        @staticmethod
        def backward(ctx, grad):
            x, w = ctx.saved_tensors
            return None, grad * w * ctx.factor, grad * x * ctx.factor

    x, w = torch.randn(4, requires_grad=True), torch.randn(4, requires_grad=True)
    outputs = [Scale.apply(3.0, x, w), torchrl_private.function_apply(Scale, 3.0, x, w)]
    assert type(outputs[0].grad_fn) is type(outputs[1].grad_fn) is torchrl_private.backward_node_class(Scale)
    grads = [torch.autograd.grad(out, (x, w)) for out in outputs]
    assert torch.equal(outputs[0], outputs[1]) and all(torch.equal(a, b) for a, b in zip(*grads))


def test_gradient_hooks_and_backward_node_class_see_what_torch_holds():
    """gradient_hooks sees a tensor hook and a post-accumulate-grad hook; backward_node_class is the
    class of the nodes a Function makes; without_loss_contexts unwraps TorchRL's loss-method wrapper."""
    weight = torch.randn(3, requires_grad=True)
    assert not torchrl_private.gradient_hooks(weight)
    handle = weight.register_hook(lambda grad: grad)
    assert torchrl_private.gradient_hooks(weight)
    handle.remove()
    assert not torchrl_private.gradient_hooks(weight)
    weight.register_post_accumulate_grad_hook(lambda parameter: None)
    assert torchrl_private.gradient_hooks(weight)

    class Square(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x):
            return x * x

        @staticmethod
        def backward(ctx, grad):
            return grad

    assert type(Square.apply(torch.randn(3, requires_grad=True)).grad_fn) is torchrl_private.backward_node_class(Square)

    class Loss(TD3Loss):
        def value_loss(self, tensordict):
            return "own"

    wrapped = Loss.__dict__["value_loss"]
    assert wrapped.__wrapped__ is not wrapped  # TorchRL's metaclass wraps the public *loss methods
    torchrl_private.without_loss_contexts(Loss, "value_loss")
    assert Loss.__dict__["value_loss"] is wrapped.__wrapped__


def test_soft_update_tensors_give_softupdate_step(td3_loss):
    import copy

    loss_a, loss_b = td3_loss, copy.deepcopy(td3_loss)
    a, b = SoftUpdate(loss_a, tau=0.1), SoftUpdate(loss_b, tau=0.1)
    for loss in (loss_a, loss_b):  # move the sources away from the targets
        with torch.no_grad():
            for p in loss.parameters():
                p.add_(0.5)
    a.step()
    sources, targets = torchrl_private.soft_update_tensors(b)
    assert len(sources) == len(targets) > 0
    for source, target in zip(sources, targets):
        target.lerp_(source, 1 - b.eps)
    assert (loss_a.target_qvalue_network_params == loss_b.target_qvalue_network_params).all()
    assert (loss_a.target_actor_network_params == loss_b.target_actor_network_params).all()


# ----------------------------------------------------------------------------- collectors
def test_collector_accessors(collector):
    carrier = torchrl_private.collector_carrier(collector)
    assert "observation" in carrier.keys() and ("collector", "traj_ids") in carrier.keys(True)
    state = collector.state_dict()
    assert state["frames"] >= 10
    replaced = carrier.clone()
    replaced["observation"] = torch.full_like(replaced["observation"], 3.0)
    torchrl_private.restore_collector(collector, state["frames"] + 5, state["iter"] + 1, replaced, state["traj_pool"])
    restored = collector.state_dict()
    assert (restored["frames"], restored["iter"]) == (state["frames"] + 5, state["iter"] + 1)
    assert torchrl_private.collector_carrier(collector) is replaced
    assert restored["traj_pool"] == state["traj_pool"]


def test_gym_env_of_unwraps_transformed_envs(env):
    gym_env = torchrl_private.gym_env_of(env)
    assert isinstance(gym_env, gymnasium.Env)
    assert gym_env.unwrapped.spec.id == "Pendulum-v1"


def test_fused_adam_step_is_optimizer_step():
    """The direct fused-Adam call gives Optimizer.step's parameters and state bit for bit, also
    after a load_state_dict (which replaces the state tensors), after ``state.clear()`` (a fresh
    Adam in the same state dict, as CEM-RL gives each member) and with weight decay."""
    import copy

    torch.manual_seed(0)
    nets = [torch.nn.Sequential(torch.nn.Linear(5, 16), torch.nn.Tanh(), torch.nn.Linear(16, 3)) for _ in range(2)]
    nets[1].load_state_dict(nets[0].state_dict())
    optimizers = [torch.optim.Adam(net.parameters(), lr=1e-2, weight_decay=1e-3, fused=True) for net in nets]
    x = torch.randn(32, 5)

    def steps(n):
        for _ in range(n):
            for net, optimizer, step in zip(nets, optimizers, (lambda o: o.step(), torchrl_private.fused_adam_step)):
                optimizer.zero_grad(set_to_none=True)
                net(x).pow(2).mean().backward()
                step(optimizer)

    steps(4)
    saved = copy.deepcopy(optimizers[0].state_dict())
    steps(3)
    for optimizer in optimizers:
        optimizer.load_state_dict(copy.deepcopy(saved))
    steps(3)
    for a, b in zip(nets[0].parameters(), nets[1].parameters()):
        assert torch.equal(a, b)
        for key in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(optimizers[0].state[a][key], optimizers[1].state[b][key])
    assert optimizers[1].state[next(nets[1].parameters())]["step"].item() == 7  # 4, back to 4 on loading, 3 more
    for optimizer in optimizers:
        optimizer.state.clear()
    steps(3)
    for a, b in zip(nets[0].parameters(), nets[1].parameters()):
        assert torch.equal(a, b)
        for key in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(optimizers[0].state[a][key], optimizers[1].state[b][key])
    assert optimizers[1].state[next(nets[1].parameters())]["step"].item() == 3  # counted from the clear


@pytest.mark.parametrize("env_id", ["HalfCheetah-v5", "Swimmer-v5", "Walker2d-v5", "Hopper-v5", "Ant-v5"])
def test_gym_mujoco_constants_hold_what_each_task_rule_reads(env_id):
    """The batched ES backend reads these private gymnasium constants per task: each must exist
    (a rename in gymnasium fails here, naming it)."""
    from torchrl_esrl.collectors.mujoco_batch import TASKS

    rules = TASKS[env_id]
    needed = {"_forward_reward_weight", "_ctrl_cost_weight", "_exclude_current_positions_from_observation"}
    if rules.healthy is not None:
        needed |= {"_healthy_reward", "_terminate_when_unhealthy", "_healthy_z_range"}
        needed |= {"_healthy_angle_range"} if env_id != "Ant-v5" else set()
        needed |= {"_healthy_state_range"} if env_id == "Hopper-v5" else set()
    if rules.contact_forces:
        needed |= {"_contact_cost_weight", "_contact_force_range", "_main_body", "_include_cfrc_ext_in_observation"}
    constants = torchrl_private.gym_mujoco_constants(gymnasium.make(env_id).unwrapped)
    missing = sorted(needed - set(constants))
    assert not missing, f"gymnasium {gymnasium.__version__} {env_id} no longer has {missing}: update torchrl_esrl/torchrl_private.py"


def test_foreach_lerp_is_lerp_per_tensor():
    generator = torch.Generator().manual_seed(0)
    targets = [torch.randn(5, 3, generator=generator), torch.randn(7, generator=generator)]
    sources = [torch.randn_like(t) for t in targets]
    expected = [t.clone().lerp_(s, 0.005) for t, s in zip(targets, sources)]
    torchrl_private.foreach_lerp_(targets, sources, 0.005)
    for got, want in zip(targets, expected):
        assert torch.equal(got, want)


def test_gym_env_state_restores_a_mujoco_episode_mid_way():
    """The snapshot of a gymnasium env's private wrapper state (TimeLimit's step count...) and its
    simulator: the restored env takes the same steps, and ends at the same time limit."""
    import numpy as np

    source, target = gymnasium.make("Hopper-v5", max_episode_steps=12), gymnasium.make("Hopper-v5", max_episode_steps=12)
    source.reset(seed=3)
    target.reset(seed=99)
    actions = np.random.default_rng(0).uniform(-1, 1, size=(12, 3)).astype(np.float32)
    for action in actions[:5]:
        source.step(action)
    torchrl_private.load_gym_env_state(target, torchrl_private.gym_env_state(source))
    for action in actions[5:]:
        expected, got = source.step(action), target.step(action)
        assert np.array_equal(expected[0], got[0]) and expected[1:4] == got[1:4]
    assert got[3] or got[2]  # the time limit (12 steps) came at the same step
