import pytest
import torch
from torchrl.data import TensorDictReplayBuffer

from torchrl_esrl import MultiBuffer
from torchrl_esrl.data.multibuffer import ratio_counts, validate_ratio
from torchrl_esrl.errors import ConfigError

from conftest import transitions


@pytest.mark.parametrize("bad", [[1, 2], [-0.1, 0.5, 0.6], [0, 0, 0], ["a", 1, 1], [float("nan"), 1, 1]])
def test_invalid_ratio_is_a_one_line_config_error(bad):
    with pytest.raises(ConfigError, match=r"^buffer\.ratio: .*allowed") as error:
        validate_ratio(bad)
    assert "\n" not in str(error.value)


def filled(ratio=(0.5, 0.2, 0.3), sizes=(300, 300, 300), **kwargs):
    buffer = MultiBuffer(ratio=ratio, capacity=1000, batch_size=256, **kwargs)
    for index, (name, size) in enumerate(zip(buffer.names, sizes)):
        buffer.extend(transitions(size, fill=float(index)), name)
    return buffer


@pytest.mark.parametrize("ratio", [(0.5, 0.2, 0.3), (0.34, 0.33, 0.33), (0.0, 0.5, 0.5), (1, 0, 0)])
@pytest.mark.parametrize("batch_size", [256, 100, 33])
def test_every_batch_holds_exactly_the_ratio(ratio, batch_size):
    buffer = filled(ratio)
    expected = ratio_counts(batch_size, ratio)
    for _ in range(5):
        batch = buffer.sample(batch_size)
        assert batch.batch_size == torch.Size([batch_size])
        counts = torch.bincount(batch["buffer"], minlength=3).tolist()
        assert counts == expected
        # the tag says where the item came from: each buffer was filled with its own index
        assert torch.equal(batch["observation"][:, 0], batch["buffer"].float())
        assert "extra" not in batch.keys()


def test_readiness_rule_of_the_paper():
    buffer = MultiBuffer(ratio=(0.5, 0.2, 0.3), capacity=1000, min_size=100)
    assert not buffer.ready()
    buffer.extend(transitions(500), "noisy")
    buffer.extend(transitions(100), "good")
    assert not buffer.ready()  # bad still empty
    buffer.extend(transitions(99), "bad")
    assert not buffer.ready()
    with pytest.raises(RuntimeError, match="not ready"):
        buffer.sample(10)
    buffer.extend(transitions(1), "bad")
    assert buffer.ready()


def test_buffers_with_zero_share_do_not_block_readiness():
    buffer = MultiBuffer(ratio=(0.0, 0.0, 1.0), capacity=1000, min_size=50)
    buffer.extend(transitions(50), "noisy")
    assert buffer.ready()
    assert torch.all(buffer.sample(64)["buffer"] == 2)


def test_renormalize_samples_only_ready_buffers():
    buffer = MultiBuffer(ratio=(0.5, 0.2, 0.3), capacity=1000, min_size=100, renormalize=True)
    assert not buffer.ready()
    buffer.extend(transitions(100, fill=2.0), "noisy")
    buffer.extend(transitions(50, fill=0.0), "good")  # below K: not sampled yet
    assert buffer.ready()
    assert buffer.counts(256) == {"good": 0, "bad": 0, "noisy": 256}
    buffer.extend(transitions(50, fill=0.0), "good")
    assert buffer.counts(80) == {"good": 50, "bad": 0, "noisy": 30}
    counts = torch.bincount(buffer.sample(80)["buffer"], minlength=3).tolist()
    assert counts == [50, 0, 30]


def test_extend_routes_by_tag_and_defaults_to_noisy():
    buffer = MultiBuffer(capacity=100)
    buffer.extend(transitions(5))
    assert buffer.sizes() == {"good": 0, "bad": 0, "noisy": 5}
    tagged = transitions(6)
    tagged["buffer"] = torch.tensor([0, 0, 1, 2, 2, 2])
    buffer.extend(tagged)
    assert buffer.sizes() == {"good": 2, "bad": 1, "noisy": 8}
    assert len(buffer) == 11
    assert isinstance(buffer.good, TensorDictReplayBuffer) and buffer["bad"] is buffer.bad


def test_state_dict_round_trip_restores_contents():
    source = filled(sizes=(10, 20, 30))
    target = MultiBuffer(ratio=(1, 1, 1), capacity=1000)
    target.load_state_dict(source.state_dict())
    assert target.sizes() == source.sizes()
    assert target.ratio == source.ratio
    assert torch.equal(target.bad[:]["observation"], source.bad[:]["observation"])


def test_dumps_and_loads_round_trip(tmp_path):
    source = filled(sizes=(10, 20, 30), min_size=5)
    source.dumps(tmp_path / "mb")
    target = MultiBuffer(capacity=1000).loads(tmp_path / "mb")
    assert target.sizes() == {"good": 10, "bad": 20, "noisy": 30}
    assert target.min_size == 5
    assert torch.equal(target.noisy[:]["next", "reward"], source.noisy[:]["next", "reward"])


def test_gather_cache_follows_load_state_dict():
    """MultiBuffer caches the storages' tensors for its gather path; loading new contents refreshes them."""
    from tensordict import TensorDict

    def filled(value):
        mb = MultiBuffer(ratio=(0.5, 0.2, 0.3), capacity=64, batch_size=32)
        for name in mb.names:
            mb.extend(TensorDict({
                "observation": torch.full((64, 3), float(value)), "action": torch.zeros(64, 1),
                "next": {"observation": torch.zeros(64, 3), "reward": torch.zeros(64, 1),
                         "done": torch.zeros(64, 1, dtype=torch.bool), "terminated": torch.zeros(64, 1, dtype=torch.bool),
                         "truncated": torch.zeros(64, 1, dtype=torch.bool)}}, [64]), name)
        return mb

    a, b = filled(1.0), filled(2.0)
    assert (a.sample()["observation"] == 1).all()
    a.load_state_dict(b.state_dict())
    assert (a.sample()["observation"] == 2).all()
    assert a.sample()["buffer"].tolist() == [0] * 16 + [1] * 6 + [2] * 10


# ------------------------------------------------------------- a TorchRL replay buffer
def test_direct_writes_store_what_torchrl_extend_stores():
    """One transition at a time (the TD3 side) and batches (ES trajectories), wrapping around the
    capacity: the same storages, lengths, writer states and samples as TorchRL's own extend."""
    direct, stock = (MultiBuffer(capacity=40, batch_size=16, direct_writes=flag) for flag in (True, False))
    for step in range(30):
        for name, n in (("noisy", 1), ("good", 1 + step % 4), ("bad", 3)):
            data = transitions(n, fill=float(step))
            data["action"] = torch.randn(n, 1)
            direct.extend(data.clone(), name)
            stock.extend(data.clone(), name)
    for name in direct.names:
        assert len(direct[name]) == len(stock[name])
        assert direct[name].writer.state_dict() == stock[name].writer.state_dict()
        assert (direct[name].storage.get(slice(0, 40)) == stock[name].storage.get(slice(0, 40))).all()
    torch.manual_seed(3)
    sample = stock.sample()
    torch.manual_seed(3)
    assert (direct.sample() == sample).all()


def test_multibuffer_is_a_torchrl_replay_buffer_ensemble():
    from torchrl.data import ReplayBuffer, ReplayBufferEnsemble
    from torchrl.data.replay_buffers import SamplerEnsemble, StorageEnsemble

    buffer = filled(sizes=(10, 20, 30))
    assert isinstance(buffer, ReplayBuffer) and isinstance(buffer, ReplayBufferEnsemble)
    assert isinstance(buffer.sampler, SamplerEnsemble) and isinstance(buffer.storage, StorageEnsemble)
    # TorchRL's integer indexing reaches the same three TensorDictReplayBuffers as the names
    assert [buffer[i] for i in range(3)] == [buffer.good, buffer.bad, buffer.noisy]
    assert all(isinstance(buffer[name], TensorDictReplayBuffer) for name in buffer.names)
    assert len(buffer) == 60 and buffer.write_count == 60
    assert not buffer.storage.fast_path()  # the reference reads through each storage's get


def test_torchrl_collector_and_trainer_drive_the_multibuffer():
    """TorchRL's Collector writes into the MultiBuffer (its data lands in ``noisy``, the default),
    TorchRL's Trainer samples it through ``ReplayBufferTrainer`` and TorchRL's DDPGLoss learns."""
    from torchrl.collectors import Collector
    from torchrl.modules import MLP, ValueOperator
    from torchrl.objectives import DDPGLoss
    from torchrl.trainers import DefaultOptimizationStepper, ReplayBufferTrainer, Trainer

    from torchrl_esrl.envs import make_env
    from torchrl_esrl.modules.networks import make_actor

    torch.manual_seed(0)
    buffer = MultiBuffer(ratio=(0.5, 0.2, 0.3), capacity=5000, batch_size=64, min_size=100)
    env = make_env("pendulum", seed=0)
    collector = Collector(env, None, frames_per_batch=200, total_frames=400, replay_buffer=buffer)
    for _ in collector:  # with a replay buffer the collector yields nothing and writes itself
        pass
    collector.shutdown()
    assert buffer.sizes() == {"good": 0, "bad": 0, "noisy": 400}
    assert buffer.write_count == 400
    # good and bad from elsewhere (the ES side in ES-TD3Buffers): tagged batches route themselves
    tagged = buffer.noisy.sample(300).select(*buffer.keys)
    tagged["buffer"] = torch.tensor([0] * 150 + [1] * 150)
    buffer.extend(tagged)
    assert buffer.sizes() == {"good": 150, "bad": 150, "noisy": 400} and buffer.ready()

    actor = make_actor(3, env.action_spec, hidden=(64, 64))
    value = ValueOperator(MLP(in_features=4, out_features=1, num_cells=[64, 64]), in_keys=["observation", "action"])
    loss = DDPGLoss(actor, value, delay_actor=False, delay_value=False)
    loss.make_value_estimator(gamma=0.9)
    held_out = buffer.sample(256)
    with torch.no_grad():
        before = loss(held_out)["loss_value"].item()
    steps = 150
    collector = Collector(make_env("pendulum", seed=1), None, frames_per_batch=100, total_frames=200)
    trainer = Trainer(
        collector=collector, total_frames=200, frame_skip=1, optim_steps_per_batch=steps, loss_module=loss,
        optimizer=torch.optim.Adam(loss.parameters(), lr=1e-3), optimization_stepper=DefaultOptimizationStepper(),
        progress_bar=False, clip_grad_norm=False,
    )
    sampled = []
    hook = ReplayBufferTrainer(buffer, batch_size=64, flatten_tensordicts=True)
    trainer.register_op("batch_process", hook.extend)  # as ReplayBufferTrainer.register, without priorities
    trainer.register_op("process_optim_batch", hook.sample)
    trainer.register_op("process_optim_batch", lambda batch: sampled.append(torch.bincount(batch["buffer"], minlength=3).tolist()) or batch)
    trainer.train()
    collector.shutdown()
    assert buffer.sizes()["noisy"] == 600  # the trainer's batches went to noisy too
    assert len(sampled) == 2 * steps and all(counts == [32, 13, 19] for counts in sampled)
    with torch.no_grad():
        after = loss(held_out)["loss_value"].item()
    assert after < 0.5 * before, (before, after)
