"""TD3 through TorchRL's TD3Loss, fed by the three buffers (real envs, small budgets)."""
import copy

import pytest
import torch
from torchrl.collectors import Collector
from torchrl.modules import MLP, ValueOperator
from torchrl.objectives import DDPGLoss, SoftUpdate, TD3Loss, ValueEstimators

from benchmarks.common import transitions as _transitions

from torchrl_esrl import MultiBuffer
from torchrl_esrl.envs import make_env
from torchrl_esrl.es.openes import OpenES
from torchrl_esrl.collectors.es_collector import ESCollector
from torchrl_esrl.modules.networks import flat_parameters, make_actor, make_critic
from torchrl_esrl.algorithm.td3_phase import td3_phase
from torchrl_esrl.collectors.td3_collector import GymTD3Collector, finished_episode_returns, make_td3_collector
from torchrl_esrl.objectives.td3 import TD3, ForeachSoftUpdate, ManualGradTD3Loss, zero_grads

FAST = {"loss_class": ManualGradTD3Loss, "target_update_class": ForeachSoftUpdate, "optimizer_impl": "fused"}  # make_td3's fast pieces
from torchrl_esrl.data.threshold import Threshold


def build(env_name, seed=0, hidden=(256, 256), **td3_kwargs):
    torch.manual_seed(seed)
    env = make_env(env_name, seed=seed)
    obs_dim = env.observation_spec["observation"].shape[-1]
    actor = make_actor(obs_dim, env.action_spec, hidden)
    critic = make_critic(obs_dim, env.action_spec.shape[-1], hidden)
    return env, actor, TD3(actor, critic, env.action_spec, **td3_kwargs)


def test_policy_delay_updates_actor_and_targets_every_second_step():
    env, actor, td3 = build("pendulum")
    buffer = MultiBuffer(ratio=(0, 0, 1), capacity=1000, batch_size=32, min_size=32)
    collector = make_td3_collector(env, td3, frames_per_batch=64)
    buffer.extend(next(iter(collector)), "noisy")
    collector.shutdown()
    target_before = td3.loss.target_qvalue_network_params.clone()
    actor_before = flat_parameters(actor)
    out = td3.update(buffer.sample())
    assert "actor_loss" not in out
    assert torch.equal(flat_parameters(actor), actor_before)
    assert (td3.loss.target_qvalue_network_params == target_before).all()
    out = td3.update(buffer.sample())
    assert "actor_loss" in out
    assert not torch.equal(flat_parameters(actor), actor_before)
    assert not (td3.loss.target_qvalue_network_params == target_before).all()


def test_exploration_noise_has_configured_scale():
    env, actor, td3 = build("halfcheetah", exploration_noise=0.1)
    td = env.reset()
    clean = actor(td.clone())["action"]
    noisy = torch.stack([td3.exploration_policy(td.clone())["action"] for _ in range(400)])
    noise = (noisy - clean).flatten()
    assert abs(noise.std().item() - 0.1) < 0.02
    assert abs(noise.mean().item()) < 0.02


def test_no_learning_before_every_buffer_holds_k():
    env, actor, td3 = build("pendulum")
    buffer = MultiBuffer(capacity=10_000, batch_size=64, min_size=500)
    collector = make_td3_collector(env, td3, frames_per_batch=100)
    stats = td3_phase(1000, iter(collector), td3, buffer)
    collector.shutdown()
    assert stats["updates"] == 0 and td3.updates == 0  # good and bad are still empty
    assert buffer.sizes() == {"good": 0, "bad": 0, "noisy": 1000}


@pytest.mark.e2e  # a real training run
def test_td3_with_three_buffers_learns_pendulum():
    """ES offspring fill good/bad through the threshold, TD3 fills noisy and learns from all three."""
    env, actor, td3 = build("pendulum", seed=1, hidden=(64, 64), lr=1e-3)
    buffer = MultiBuffer(ratio=(0.5, 0.2, 0.3), capacity=50_000, batch_size=128, min_size=256)
    threshold = Threshold(0.9)
    es = OpenES(flat_parameters(actor), population_size=10, sigma=0.02, lr=0.01, generator=torch.Generator().manual_seed(1))
    es_collector = ESCollector("pendulum", actor, seed=1)
    collector = make_td3_collector(env, td3, frames_per_batch=50)
    batches = iter(collector)
    before = es_collector.evaluate_policy(flat_parameters(actor), 5).returns.mean().item()
    for _ in range(6):
        for _ in range(2):
            population = es.ask()
            generation = es_collector.evaluate(population)
            good = threshold.route(generation.returns)
            buffer.extend(generation.transitions[generation.member_mask(good)], "good")
            buffer.extend(generation.transitions[generation.member_mask(~good)], "bad")
            es.tell(population, generation.returns)
        td3_phase(1000, batches, td3, buffer, on_episode=threshold.observe)
    collector.shutdown()
    after = es_collector.evaluate_policy(flat_parameters(actor), 5).returns.mean().item()
    assert td3.updates >= 4000
    assert min(buffer.sizes().values()) >= 256
    assert before < -900, before  # Pendulum-v1: random and untrained policies score about -1200
    assert after > -800 and after - before > 400, (before, after)


def test_multibuffer_is_a_drop_in_buffer_for_another_torchrl_loss():
    """DDPGLoss (not TD3) trained from MultiBuffer batches of real Pendulum transitions."""
    torch.manual_seed(0)
    env = make_env("pendulum", seed=0)
    actor = make_actor(3, env.action_spec, hidden=(64, 64))
    value = ValueOperator(MLP(in_features=4, out_features=1, num_cells=[64, 64]), in_keys=["observation", "action"])
    loss = DDPGLoss(actor, value, delay_actor=True, delay_value=True)
    loss.make_value_estimator(gamma=0.9)
    optimizer = torch.optim.Adam(loss.parameters(), lr=1e-3)
    buffer = MultiBuffer(ratio=(0.5, 0.0, 0.5), capacity=5000, batch_size=128, min_size=200)
    collector = Collector(env, None, frames_per_batch=400, total_frames=800)  # random actions
    for index, data in enumerate(collector):
        buffer.extend(data, "good" if index == 0 else "noisy")
    collector.shutdown()
    assert finished_episode_returns(data)  # Pendulum episodes are 200 frames: two ended
    held_out = buffer.sample(256)
    with torch.no_grad():
        before = loss(held_out)["loss_value"].item()
    for _ in range(300):
        losses = loss(buffer.sample())
        optimizer.zero_grad()
        (losses["loss_value"] + losses["loss_actor"]).backward()
        optimizer.step()
    with torch.no_grad():
        after = loss(held_out)["loss_value"].item()
    assert after < 0.5 * before, (before, after)


def test_fast_td3_matches_stock_torchrl_td3():
    """The default (Q1-only actor loss, foreach soft update, fused Adam) gives stock TD3Loss's
    losses, parameters and target parameters on the same batches and noise."""
    import copy

    from torchrl.data import Bounded

    torch.manual_seed(0)
    spec = Bounded(-torch.ones(6), torch.ones(6), shape=(6,))
    actor, critic = make_actor(17, spec), make_critic(17, 6)
    torch.manual_seed(1)  # TD3Loss draws the second critic's initial weights
    stock = TD3(copy.deepcopy(actor), copy.deepcopy(critic), spec)
    torch.manual_seed(1)
    fast = TD3(actor, critic, spec, **FAST)
    assert type(stock.loss).__name__ == "TD3Loss" and type(fast.loss).__name__ == "ManualGradTD3Loss"
    buffer = MultiBuffer(capacity=512, batch_size=256)
    for name in buffer.names:
        buffer.extend(_random_transitions(512, 17, 6), name)
    for step in range(10):
        batch = buffer.sample()
        batch["next", "terminated"][::9] = True  # bootstrapping cut on some transitions
        torch.manual_seed(100 + step)
        out_stock = stock.update(batch)
        torch.manual_seed(100 + step)
        out_fast = fast.update(batch)
        assert out_stock.keys() == out_fast.keys()
        for key in out_stock:
            assert abs(out_stock[key] - out_fast[key]) <= 1e-5 * max(1.0, abs(out_stock[key])), (step, key)
    for a, b in zip(stock.loss.parameters(), fast.loss.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    for name in ("target_actor_network_params", "target_qvalue_network_params"):
        torch.testing.assert_close(getattr(stock.loss, name).to_dict(), getattr(fast.loss, name).to_dict(), rtol=1e-5, atol=1e-6)


def test_q1_actor_loss_gradient_equals_td3loss():
    from torchrl.data import Bounded
    from torchrl.objectives import TD3Loss

    from torchrl_esrl.objectives.manual_grad import ManualGradTD3Loss, TD3LossQ1Actor

    torch.manual_seed(0)
    spec = Bounded(-torch.ones(6), torch.ones(6), shape=(6,))
    actor, critic = make_actor(17, spec), make_critic(17, 6)
    batch = _random_transitions(256, 17, 6)
    grads, values = [], []
    for cls in (TD3Loss, TD3LossQ1Actor, ManualGradTD3Loss):
        torch.manual_seed(1)
        loss = cls(actor_network=actor, qvalue_network=critic, action_spec=spec, num_qvalue_nets=2, loss_function="l2")
        assert cls is not ManualGradTD3Loss or loss.refusal() is None, "the hand-written path must be the one under test"
        loss_actor, _ = loss.actor_loss(batch)
        actor.zero_grad()
        loss_actor.backward()
        values.append(loss_actor.detach())
        grads.append(torch.cat([p.grad.flatten() for p in actor.parameters()]))
    for value, grad in zip(values[1:], grads[1:]):
        torch.testing.assert_close(value, values[0])
        torch.testing.assert_close(grad, grads[0], rtol=1e-5, atol=1e-7)


def test_manual_grad_value_loss_equals_td3loss():
    """ManualGradTD3Loss.value_loss (stacked twin critics, hand-chained target actor) gives stock
    TD3Loss.value_loss's loss, metadata and critic gradients, with targets differing from the
    online networks, bounds other than [-1, 1] and some terminated transitions."""
    from torchrl.objectives import TD3Loss

    from torchrl_esrl.objectives.td3 import ManualGradTD3Loss

    spec, actor, critic, batch = _critic_case(256, terminated_every=5)
    results = []
    for cls in (TD3Loss, ManualGradTD3Loss):
        loss = _loss_with_moved_targets(cls, actor, critic, spec)
        torch.manual_seed(3)
        value, metadata = loss.value_loss(batch)
        value.backward()
        grads = [p.grad.clone() for p in loss.qvalue_network_params.values(True, True)]
        results.append((value.detach(), metadata, grads))
    (stock_value, stock_meta, stock_grads), (manual_value, manual_meta, manual_grads) = results
    assert isinstance(results[1][0], torch.Tensor) and stock_value.item() > 0
    torch.testing.assert_close(manual_value, stock_value)
    assert stock_meta.keys() == manual_meta.keys()
    for key in stock_meta:
        torch.testing.assert_close(manual_meta[key], stock_meta[key])
    for a, b in zip(stock_grads, manual_grads):
        torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-7)


def _critic_case(batch_size, terminated_every, activation="relu"):
    """Bounds other than [-1, 1], the paper's networks (critic activation as given) and a batch
    with some terminated transitions: the case the critic-loss equality tests compare."""
    from torchrl.data import Bounded

    torch.manual_seed(0)
    spec = Bounded(-2 * torch.ones(6), torch.linspace(0.5, 3.0, 6), shape=(6,))
    actor, critic = make_actor(17, spec), make_critic(17, 6, activation=activation)
    batch = _random_transitions(batch_size, 17, 6)
    batch["next", "terminated"][::terminated_every] = True
    return spec, actor, critic, batch


def _loss_with_moved_targets(cls, actor, critic, spec):
    """A TD3 loss (stock or hand-written, same seeded critics) whose target networks differ from the
    online ones, so that a mix-up of the two shows in the critic loss."""
    from torchrl.objectives import TD3Loss

    torch.manual_seed(1)
    loss = cls(actor_network=actor, qvalue_network=critic, action_spec=spec, num_qvalue_nets=2, delay_actor=True, delay_qvalue=True, loss_function="l2")
    loss.make_value_estimator(gamma=0.97)
    assert cls is TD3Loss or loss.refusal() is None, "the hand-written path must be the one under test"
    torch.manual_seed(2)
    with torch.no_grad():
        for target in (loss.target_actor_network_params, loss.target_qvalue_network_params):
            for key, value in target.items(True, True):
                if "action_" not in str(key):
                    value.add_(0.05 * torch.randn_like(value))
    return loss


def _random_transitions(n, obs_dim, act_dim):
    from benchmarks.common import transitions

    return transitions(n, obs_dim, act_dim, torch.Generator().manual_seed(n))


def _collector_pair_batches(fast, frames_per_batch, batches, seed=3, env_id="HalfCheetah-v5", noise_moments=None):
    import copy

    from torchrl_esrl.envs import make_env

    env = make_env(env_id, seed=seed, max_episode_steps=60)  # short episodes: resets inside batches
    observation_dim, action_dim = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
    torch.manual_seed(0)
    actor, critic = make_actor(observation_dim, env.action_spec), make_critic(observation_dim, action_dim)
    td3 = TD3(copy.deepcopy(actor), critic, env.action_spec)
    if noise_moments is not None:  # AdditiveGaussianModule's mean and std, other than 0 and 1
        noise = td3.exploration_policy[1]
        noise.mean.fill_(noise_moments[0])
        noise.std.fill_(noise_moments[1])
    collector = GymTD3Collector(env, td3, frames_per_batch) if fast else make_td3_collector(env, td3, frames_per_batch)
    assert not fast or collector.numpy_steps is not None, "the numpy steps after the actor's tanh must be the path under test"
    torch.manual_seed(7)  # the exploration noise stream
    iterator = iter(collector)
    return [next(iterator) for _ in range(batches)]


@pytest.mark.parametrize(
    ("env_id", "noise_moments"), [("HalfCheetah-v5", None), ("InvertedPendulum-v5", (0.05, 1.5))]
)  # action bounds 1 and 3; the noise's own mean and std
def test_gym_td3_collector_equals_torchrl_collector(env_id, noise_moments):
    """GymTD3Collector (the fast stepping path) yields the transitions TorchRL's GymEnv +
    Collector yield: same seed, same actor, same noise stream -> identical transition keys,
    finished-episode returns included, across episode ends."""
    from torchrl_esrl.data.multibuffer import TRANSITION_KEYS

    for frames_per_batch, count in ((1, 130), (25, 6)):
        reference = torch.cat(_collector_pair_batches(False, frames_per_batch, count, env_id=env_id, noise_moments=noise_moments))
        fast = torch.cat(_collector_pair_batches(True, frames_per_batch, count, env_id=env_id, noise_moments=noise_moments))
        assert reference["next", "done"].sum() >= 2  # episodes ended inside the window
        for key in (*TRANSITION_KEYS, ("next", "episode_reward")):
            assert torch.equal(reference.get(key), fast.get(key)), (frames_per_batch, key)
        assert finished_episode_returns(reference) == finished_episode_returns(fast)


@pytest.mark.parametrize("fast", [True, False])
def test_td3_collector_resumes_mid_episode(fast):
    """TD3EnvState restores a fresh collector (the fast path or TorchRL's Collector) mid-episode:
    it continues with exactly the frames the uninterrupted collector produces."""
    import copy

    from torchrl_esrl.collectors.td3_collector import TD3EnvState
    from torchrl_esrl.data.multibuffer import TRANSITION_KEYS
    from torchrl_esrl.envs import make_env

    def collector(seed):
        env = make_env("HalfCheetah-v5", seed=seed, max_episode_steps=60)
        torch.manual_seed(0)
        td3 = TD3(make_actor(17, env.action_spec), make_critic(17, 6), env.action_spec)
        return GymTD3Collector(env, td3, 10) if fast else make_td3_collector(env, td3, frames_per_batch=10)

    first = collector(3)
    batches = iter(first)
    for _ in range(7):  # 70 frames: mid-way through the second episode
        next(batches)
    state = copy.deepcopy(TD3EnvState(first).state_dict())
    torch.manual_seed(11)
    expected = torch.cat([next(batches) for _ in range(8)])
    resumed = collector(99)  # another seed: everything must come from the state
    TD3EnvState(resumed).load_state_dict(state)
    torch.manual_seed(11)
    batches = iter(resumed)
    got = torch.cat([next(batches) for _ in range(8)])
    assert expected["next", "done"].any()
    for key in (*TRANSITION_KEYS, ("next", "episode_reward")):
        assert torch.equal(got.get(key), expected.get(key)), key


def test_manual_grad_loss_follows_a_loaded_state_dict():
    """The hand-written losses look their tensors up once; loading a checkpoint (TorchRL copies into the
    parameters in place) must still give the loaded learner's losses."""
    import copy

    from torchrl.data import Bounded

    spec = Bounded(-torch.ones(6), torch.ones(6), shape=(6,))
    batch = _random_transitions(64, 17, 6)
    source, loaded = (TD3(make_actor(17, spec, (32, 32)), make_critic(17, 6, (32, 32)), spec, **FAST) for _ in range(2))
    for _ in range(3):
        source.update(batch)
        loaded.update(batch)
    loaded.load_state_dict(copy.deepcopy(source.state_dict()))
    results = []
    for td3 in (source, loaded):
        torch.manual_seed(5)
        results.append((td3.loss.value_loss(batch)[0].item(), td3.loss.actor_loss(batch)[0].item(), td3.update(batch)))
    assert results[0] == results[1]


@pytest.mark.parametrize("activation", ["relu", "tanh"])
def test_value_loss_backward_equals_td3loss_backward(activation):
    """ManualGradTD3Loss.value_loss + backward (the chain rule inside a torch.autograd.Function)
    against stock TD3Loss.value_loss + backward: same loss, same gradients, with targets
    differing from the online networks, non-unit bounds and terminated transitions."""
    from torchrl.objectives import TD3Loss

    from torchrl_esrl.objectives.td3 import ManualGradTD3Loss

    spec, actor, critic, batch = _critic_case(200, terminated_every=7, activation=activation)
    results = []
    for cls in (TD3Loss, ManualGradTD3Loss):
        loss = _loss_with_moved_targets(cls, actor, critic, spec)
        torch.manual_seed(3)
        value, _ = loss.value_loss(batch)
        assert cls is TD3Loss or type(value.grad_fn).__name__ == "_CriticLossBackward"
        value.backward()
        results.append((value.detach(), [p.grad.clone() for p in loss.qvalue_network_params.values(True, True)]))
    (stock_value, stock_grads), (manual_value, manual_grads) = results
    torch.testing.assert_close(manual_value, stock_value)
    assert len(stock_grads) == len(manual_grads) == 6
    for a, b in zip(stock_grads, manual_grads):
        assert a.shape == b.shape and a.abs().sum() > 0
        torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("bounds", ["unit", "other"])
def test_actor_loss_backward_equals_td3loss_backward(bounds):
    """ManualGradTD3Loss.actor_loss + backward (the chain rule inside a torch.autograd.Function)
    against stock TD3Loss.actor_loss + backward: same loss, same actor gradients, critics left
    without any."""
    from torchrl.data import Bounded
    from torchrl.objectives import TD3Loss

    from torchrl_esrl.objectives.td3 import ManualGradTD3Loss

    torch.manual_seed(0)
    low, high = (-torch.ones(6), torch.ones(6)) if bounds == "unit" else (-2 * torch.ones(6), torch.linspace(0.5, 3.0, 6))
    spec = Bounded(low, high, shape=(6,))
    actor, critic = make_actor(17, spec), make_critic(17, 6)
    batch = _random_transitions(200, 17, 6)
    results = []
    for cls in (TD3Loss, ManualGradTD3Loss):
        torch.manual_seed(1)  # the loss draws its critics' parameters
        loss = cls(actor_network=actor, qvalue_network=critic, action_spec=spec, num_qvalue_nets=2, loss_function="l2")
        actor.zero_grad(set_to_none=True)
        value, _ = loss.actor_loss(batch)
        assert cls is TD3Loss or type(value.grad_fn).__name__ == "_ActorLossBackward"
        value.backward()
        assert all(p.grad is None for p in loss.qvalue_network_params.values(True, True))
        results.append((value.detach(), [p.grad.clone() for p in actor.parameters()]))
    (stock_value, stock_grads), (manual_value, manual_grads) = results
    torch.testing.assert_close(manual_value, stock_value)
    assert len(stock_grads) == len(manual_grads) == 6
    for a, b in zip(stock_grads, manual_grads):
        assert a.abs().sum() > 0
        torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-7)


# ------------------------------------------------- edits a researcher makes, fast pieces against the reference
REFERENCE = {"loss_class": TD3Loss, "target_update_class": SoftUpdate, "optimizer_impl": "default"}


class _L2TD3(TD3):
    """TD3 with an L2 penalty on every trained parameter, added to each loss."""

    def backward(self, loss, optimizer):
        super().backward(loss + 1e-1 * sum(p.pow(2).sum() for p in optimizer.param_groups[0]["params"]), optimizer)


class _ClippedTD3(TD3):
    """TD3 that clips each network's gradient norm after backward."""

    def backward(self, loss, optimizer):
        super().backward(loss, optimizer)
        torch.nn.utils.clip_grad_norm_(optimizer.param_groups[0]["params"], 0.05)


def _scale_gradients(td3):
    """Gradient hooks on the actor's and the critics' first weights: rows alternately zeroed and halved
    (Adam undoes a constant scale: the zeroed rows are what shows)."""
    for weight in (td3.actor[0].module[0].weight, td3.loss.qvalue_network_params.get(("module", "0", "weight"))):
        scale = torch.where(torch.arange(weight.shape[-2]) % 2 == 0, 0.0, 0.5).unsqueeze(-1)
        weight.register_hook(lambda grad, scale=scale: grad * scale)


def _clip_in_step_pre_hook(td3):
    """clip_grad_norm_ in the optimizers' step pre-hooks (fused Adam's direct kernel call must run them)."""
    def clip(optimizer, args, kwargs):
        torch.nn.utils.clip_grad_norm_(optimizer.param_groups[0]["params"], 0.05)

    for optimizer in (td3.actor_optimizer, td3.critic_optimizer):
        optimizer.register_step_pre_hook(clip)


def _freeze_actor_layer(td3):
    td3.actor[0].module[0].requires_grad_(False)


def _freeze_critic_layer(td3):
    for key in (("module", "0", "weight"), ("module", "0", "bias")):
        td3.loss.qvalue_network_params.get(key).requires_grad_(False)


def _td3_runs(pieces, td3_class=TD3, edit=None, updates=5, **kwargs):
    """(TD3, its update outputs) after ``updates`` updates (policy delay 2) from fixed initial weights,
    on fixed batches (some terminated) and noise."""
    from torchrl.data import Bounded

    spec = Bounded(-torch.ones(6), torch.ones(6), shape=(6,))
    torch.manual_seed(0)
    actor, critic = make_actor(17, spec, (64, 64)), make_critic(17, 6, (64, 64))
    generator = torch.Generator().manual_seed(0)
    batches = [_transitions(128, 17, 6, generator) for _ in range(updates)]
    for batch in batches:
        batch["next", "terminated"][::9] = True
    torch.manual_seed(1)  # TD3Loss draws the other critics' initial weights
    td3 = td3_class(copy.deepcopy(actor), copy.deepcopy(critic), spec, policy_delay=2, **pieces, **kwargs)
    if edit is not None:
        edit(td3)
    outs = []
    for step, batch in enumerate(batches):
        torch.manual_seed(100 + step)
        outs.append(td3.update(batch))
    return td3, outs


def _state(td3) -> dict:
    return {
        "parameters": [p.detach().clone() for p in td3.loss.parameters()],
        "targets": [td3.loss.target_actor_network_params.to_dict(), td3.loss.target_qvalue_network_params.to_dict()],
    }


EDITS = {
    "l2_term": {"td3_class": _L2TD3},
    "clip_grad_norm": {"td3_class": _ClippedTD3},
    "gradient_hook": {"edit": _scale_gradients},
    "clip_in_step_pre_hook": {"edit": _clip_in_step_pre_hook},
    "frozen_actor_layer": {"edit": _freeze_actor_layer},
    "frozen_critic_layer": {"edit": _freeze_critic_layer},
    "num_qvalue_nets_1": {"num_qvalue_nets": 1},
    "num_qvalue_nets_3": {"num_qvalue_nets": 3},
}


@pytest.mark.parametrize("name", list(EDITS))
def test_an_edit_gives_the_fast_pieces_the_references_result(name):
    """Each edit (a loss term or gradient clipping in TD3.backward, gradient or optimizer hooks, frozen
    layers, 1 or 3 critics) changes the run, and the fast pieces (ManualGradTD3Loss, ForeachSoftUpdate,
    fused Adam) still give the reference's (TD3Loss, SoftUpdate, Adam) losses and parameters."""
    edit = EDITS[name]
    reference, reference_outs = _td3_runs(REFERENCE, **edit)
    fast, fast_outs = _td3_runs(FAST, **edit)
    unedited, unedited_outs = _td3_runs(FAST)
    expected = f"num_qvalue_nets={edit['num_qvalue_nets']}" if "num_qvalue_nets" in edit else None
    assert fast.loss.refusal() == expected
    assert [out.keys() for out in fast_outs] == [out.keys() for out in reference_outs]
    torch.testing.assert_close(fast_outs, reference_outs, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(_state(fast), _state(reference), rtol=1e-5, atol=1e-6)
    # the edit reached the run: far beyond the tolerance above from the unedited one
    if "num_qvalue_nets" in edit:
        assert fast.loss.qvalue_network_params.get(("module", "0", "weight")).shape[0] == edit["num_qvalue_nets"]
        assert fast_outs[-1]["critic_loss"] != pytest.approx(unedited_outs[-1]["critic_loss"], rel=1e-3)
    else:
        moved = max((a - b).abs().max().item() for a, b in zip(_state(fast)["parameters"], _state(unedited)["parameters"]))
        assert moved > 1e-4, moved
    if name.startswith("frozen"):
        initial = _td3_runs(FAST, updates=0, **edit)[0]
        frozen = [(p, q) for p, q in zip(fast.loss.parameters(), initial.loss.parameters()) if not p.requires_grad]
        assert len(frozen) == 2 and all(torch.equal(p, q) and p.grad is None for p, q in frozen)
        moving = [(p, q) for p, q in zip(unedited.loss.parameters(), initial.loss.parameters()) if q.requires_grad is False]
        assert len(moving) == 2 and not any(torch.equal(p, q) for p, q in moving)  # they move when not frozen


def test_loss_gradient_is_scaled_by_the_incoming_gradient_and_accumulates_without_rounding():
    """The hand-written backward multiplies by the loss's incoming gradient (2 * loss: twice the
    gradients, as TD3Loss), and autograd writes it into an empty .grad as it came out of the backward."""
    from torchrl.data import Bounded

    spec = Bounded(-torch.ones(6), torch.ones(6), shape=(6,))
    batch = _random_transitions(64, 17, 6)
    torch.manual_seed(0)
    actor, critic = make_actor(17, spec, (32, 32)), make_critic(17, 6, (32, 32))
    grads = {}
    for cls in (TD3Loss, ManualGradTD3Loss):
        torch.manual_seed(1)
        loss = cls(actor_network=actor, qvalue_network=critic, action_spec=spec, num_qvalue_nets=2, loss_function="l2")
        for which, parameters in (("value", list(loss.qvalue_network_params.values(True, True))), ("actor", list(actor.parameters()))):
            for scale in (1.0, 2.0):
                torch.manual_seed(3)
                value = getattr(loss, f"{which}_loss")(batch)[0]
                for p in parameters:
                    p.grad = None
                if cls is ManualGradTD3Loss and scale == 1.0:  # .grad holds what the Function's backward returned
                    direct = torch.autograd.grad(value, parameters, retain_graph=True)
                (scale * value).backward()
                grads[cls, which, scale] = [p.grad.clone() for p in parameters]
                if cls is ManualGradTD3Loss and scale == 1.0:
                    assert all(torch.equal(a, b) for a, b in zip(direct, grads[cls, which, scale]))
    for which in ("value", "actor"):
        assert all(torch.equal(2 * a, b) for a, b in zip(grads[ManualGradTD3Loss, which, 1.0], grads[ManualGradTD3Loss, which, 2.0]))
        torch.testing.assert_close(grads[ManualGradTD3Loss, which, 2.0], grads[TD3Loss, which, 2.0], rtol=1e-5, atol=1e-6)


def _manual_losses(seed=0):
    """A ManualGradTD3Loss on fixed weights and a batch: (loss module, its critic and actor parameters, batch)."""
    from torchrl.data import Bounded

    spec = Bounded(-torch.ones(6), torch.ones(6), shape=(6,))
    torch.manual_seed(seed)
    actor, critic = make_actor(17, spec, (32, 32)), make_critic(17, 6, (32, 32))
    loss = ManualGradTD3Loss(actor_network=actor, qvalue_network=critic, action_spec=spec, num_qvalue_nets=2, loss_function="l2")
    return loss, {"value": list(loss.qvalue_network_params.values(True, True)), "actor": list(actor.parameters())}, _random_transitions(64, 17, 6)


def _grads_after(which, run_backward, watch=None):
    """The .grad of ``which`` loss's parameters after ``run_backward(loss_tensor)``; ``watch(loss_tensor,
    parameters)`` first registers what must see the backward and returns how many calls it saw."""
    loss, parameters, batch = _manual_losses()
    torch.manual_seed(3)
    value = getattr(loss, f"{which}_loss")(batch)[0]
    calls = watch(value, parameters[which]) if watch else None
    run_backward(value)
    return [p.grad for p in parameters[which]], calls, value


def _watch_parameter_hook(value, parameters):
    calls = []
    parameters[-1].register_hook(lambda grad: calls.append(1))
    return calls


def _watch_post_accumulate_hook(value, parameters):
    calls = []
    parameters[0].register_post_accumulate_grad_hook(lambda p: calls.append(1))
    return calls


def _watch_loss_hook(value, parameters):
    calls = []
    value.register_hook(lambda grad: calls.append(1))
    return calls


def _watch_node_hook(value, parameters):
    calls = []
    value.grad_fn.register_hook(lambda grad_inputs, grad_outputs: calls.append(1))
    return calls


def _watch_node_prehook(value, parameters):
    calls = []
    value.grad_fn.register_prehook(lambda grad_outputs: calls.append(1))
    return calls


def _watch_retained_grad(value, parameters):
    value.retain_grad()
    return [1]


WATCHERS = [_watch_parameter_hook, _watch_post_accumulate_hook, _watch_loss_hook, _watch_node_hook, _watch_node_prehook, _watch_retained_grad]


@pytest.mark.parametrize("which", ["value", "actor"])
def test_the_direct_backward_puts_what_loss_backward_puts_into_grad(which):
    """manual_grad.backward (what TD3.backward calls) leaves .grad bit for bit as loss.backward() does,
    frees the graph as it does (a second backward fails the same way), and where anything watches the
    backward (a hook on a parameter, the loss or its node, a retained gradient) the engine runs it."""
    from torchrl_esrl.objectives.manual_grad import backward

    engine, _, _ = _grads_after(which, lambda value: value.backward())
    direct, _, value = _grads_after(which, backward)
    assert all(torch.equal(a, b) and a.stride() == b.stride() for a, b in zip(direct, engine))
    with pytest.raises(RuntimeError, match="backward through the graph a second time"):
        value.backward()
    for watch in WATCHERS:
        watched, calls, value = _grads_after(which, backward, watch)
        assert calls, watch.__name__  # the hook ran: the engine did the backward
        assert all(torch.equal(a, b) for a, b in zip(watched, engine)), watch.__name__
    # a .grad already there is added to, as by the engine
    loss, parameters, batch = _manual_losses()
    for p in parameters[which]:
        p.grad = torch.ones_like(p)
    torch.manual_seed(3)
    backward(getattr(loss, f"{which}_loss")(batch)[0])
    assert all(torch.equal(p.grad, g + 1) for p, g in zip(parameters[which], engine))


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        (lambda loss: setattr(loss, "loss_function", "smooth_l1"), "loss_function=smooth_l1"),
        (lambda loss: setattr(loss, "reduction", "sum"), "reduction=sum"),
        (lambda loss: loss.make_value_estimator(ValueEstimators.TD1, gamma=0.99), "value estimator TD1Estimator"),
        (lambda loss: loss.actor_network.module[0].module[0].register_forward_hook(lambda *args: None), "module hooks"),
    ],
)
def test_the_fast_loss_hands_what_it_does_not_compute_to_td3loss(change, reason):
    """A setting the hand-written path does not compute: refusal() says which, and value_loss and
    actor_loss are TD3Loss's own (same values as stock TD3Loss with the same setting)."""
    from torchrl.data import Bounded

    spec = Bounded(-torch.ones(6), torch.ones(6), shape=(6,))
    batch = _random_transitions(64, 17, 6)
    torch.manual_seed(0)
    actor, critic = make_actor(17, spec, (32, 32)), make_critic(17, 6, (32, 32))
    values = []
    for cls in (TD3Loss, ManualGradTD3Loss):
        torch.manual_seed(1)
        loss = cls(actor_network=copy.deepcopy(actor), qvalue_network=copy.deepcopy(critic), action_spec=spec, num_qvalue_nets=2, loss_function="l2")
        loss.make_value_estimator(gamma=0.99)
        assert cls is TD3Loss or loss.refusal() is None
        change(loss)
        assert cls is TD3Loss or loss.refusal(batch) == reason
        torch.manual_seed(3)
        value, actor_value = loss.value_loss(batch)[0], loss.actor_loss(batch)[0]
        assert type(value.grad_fn).__name__ != "_CriticLossBackward" and type(actor_value.grad_fn).__name__ != "_ActorLossBackward"
        values.append((value.detach(), actor_value.detach()))
    assert torch.equal(values[0][0], values[1][0]) and torch.equal(values[0][1], values[1][1])


def test_a_subclass_overriding_what_the_fast_loss_skips_gets_td3loss():
    """A subclass overriding a TD3Loss member that the hand-written path does not call (here the
    reduction) is computed by TD3Loss's code, with its override: stock TD3Loss's summed loss."""
    from torchrl.data import Bounded

    class SummedReduction(ManualGradTD3Loss):
        def _reduce_loss(self, loss, tensordict=None, weights=None):
            return loss.sum()

    spec = Bounded(-torch.ones(6), torch.ones(6), shape=(6,))
    torch.manual_seed(0)
    actor, critic = make_actor(17, spec, (32, 32)), make_critic(17, 6, (32, 32))
    batch = _random_transitions(64, 17, 6)
    values = []
    for cls, reduction in ((SummedReduction, "mean"), (TD3Loss, "sum"), (ManualGradTD3Loss, "mean")):
        torch.manual_seed(1)
        loss = cls(actor_network=actor, qvalue_network=critic, action_spec=spec, num_qvalue_nets=2, loss_function="l2", reduction=reduction)
        torch.manual_seed(3)
        values.append(loss.value_loss(batch)[0].item())
        if cls is SummedReduction:
            assert loss.refusal() == "SummedReduction overrides _reduce_loss"
    assert values[0] == pytest.approx(values[1], rel=1e-6) and values[0] == pytest.approx(64 * values[2], rel=1e-5)


def test_zero_grads_is_zero_grad_set_to_none():
    """zero_grads leaves every .grad None, as Optimizer.zero_grad(set_to_none=True); an optimizer
    class with its own zero_grad gets that one called."""
    net = torch.nn.Linear(3, 2)
    optimizer = torch.optim.Adam(net.parameters(), fused=True)
    net(torch.randn(4, 3)).sum().backward()
    assert all(p.grad is not None for p in net.parameters())
    zero_grads(optimizer)
    assert all(p.grad is None for p in net.parameters())

    class Zeroing(torch.optim.Adam):
        def zero_grad(self, set_to_none=True):
            super().zero_grad(set_to_none=False)

    optimizer = Zeroing(net.parameters())
    net(torch.randn(4, 3)).sum().backward()
    zero_grads(optimizer)
    assert all(p.grad is not None and not p.grad.any() for p in net.parameters())


# ------------------------------------------------- td3.precision=bf16: the losses under autocast to bfloat16
def _relative(got, expected) -> float:
    return ((got.double() - expected.double()).norm() / expected.double().norm()).item()


@pytest.mark.parametrize("which", ["value", "actor"])
def test_under_autocast_to_bfloat16_the_fast_losses_compute_td3losss_function_in_bfloat16(which):
    """Inside ``torch.autocast(dtype=torch.bfloat16)`` the hand-written losses run (they do not hand
    over) with bfloat16 products: their loss and gradients equal TD3Loss's under the same autocast to
    bfloat16 rounding, differ from the float32 ones by more than float32 rounding, and the gradients
    are float32 like the parameters."""
    spec, actor, critic, batch = _critic_case(256, terminated_every=7)
    results = {}
    for cls, bf16 in ((TD3Loss, True), (ManualGradTD3Loss, True), (ManualGradTD3Loss, False)):
        loss = _loss_with_moved_targets(cls, actor, critic, spec)
        actor.zero_grad(set_to_none=True)
        torch.manual_seed(3)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            assert cls is TD3Loss or (loss.refusal(batch), loss.matmul_dtype()) == (None, torch.bfloat16 if bf16 else None)
            value, _ = getattr(loss, f"{which}_loss")(batch)
        assert cls is TD3Loss or type(value.grad_fn).__name__ == ("_CriticLossBackward" if which == "value" else "_ActorLossBackward")
        value.backward()
        parameters = list(loss.qvalue_network_params.values(True, True)) if which == "value" else list(actor.parameters())
        assert value.dtype == torch.float32 and all(p.grad.dtype == torch.float32 for p in parameters)
        results[cls, bf16] = (value.detach(), [p.grad.clone() for p in parameters])
    (stock, stock_grads), (bf16, bf16_grads), (fp32, fp32_grads) = results.values()
    assert abs(bf16 - stock) / abs(stock) < 1e-3
    assert all(_relative(got, expected) < 0.1 for got, expected in zip(bf16_grads, stock_grads))
    assert max(_relative(got, expected) for got, expected in zip(bf16_grads, fp32_grads)) > 1e-3  # bfloat16, not float32


def test_autocast_to_float16_hands_the_losses_to_td3loss():
    spec, actor, critic, batch = _critic_case(64, terminated_every=7)
    loss = _loss_with_moved_targets(ManualGradTD3Loss, actor, critic, spec)
    with torch.autocast("cpu", dtype=torch.float16):
        assert loss.refusal(batch) == "autocast to float16"
        assert type(loss.value_loss(batch)[0].grad_fn).__name__ != "_CriticLossBackward"


@pytest.mark.parametrize("pieces", ["fast", "reference"])
def test_bf16_updates_keep_float32_weights_adam_and_targets_and_follow_the_float32_run(pieces):
    """``TD3(precision="bf16")``: after updates the parameters, their Adam moments and the targets are
    float32; the losses follow the float32 run's to bfloat16 rounding, and the parameters moved
    differently (the option reached the arithmetic). The fast pieces and the reference agree."""
    chosen = FAST if pieces == "fast" else REFERENCE
    bf16, bf16_outs = _td3_runs(chosen, precision="bf16")
    fp32, fp32_outs = _td3_runs(chosen)
    state = _state(bf16)
    assert all(p.dtype == torch.float32 for p in state["parameters"])
    targets = (bf16.loss.target_actor_network_params, bf16.loss.target_qvalue_network_params)
    assert all(v.dtype == torch.float32 for target in targets for v in target.values(True, True) if v.is_floating_point())
    moments = [s for optimizer in (bf16.actor_optimizer, bf16.critic_optimizer) for s in optimizer.state.values()]
    assert moments and all(s["exp_avg"].dtype == torch.float32 for s in moments)
    for got, expected in zip(bf16_outs, fp32_outs):
        assert got.keys() == expected.keys()
        assert all(got[key] == pytest.approx(expected[key], rel=2e-2) for key in got)
    moved = max((a - b).abs().max().item() for a, b in zip(state["parameters"], _state(fp32)["parameters"]))
    assert moved > 1e-4  # float32 rounding moves them by under 1e-6 (test_an_edit_gives_the_fast_pieces_the_references_result)
    reference, reference_outs = _td3_runs(REFERENCE, precision="bf16")
    assert all(got[key] == pytest.approx(expected[key], rel=2e-2) for got, expected in zip(bf16_outs, reference_outs) for key in got)


def test_precision_is_fp32_or_bf16():
    with pytest.raises(ValueError, match="precision must be fp32 or bf16"):
        build("pendulum", precision="fp16")
