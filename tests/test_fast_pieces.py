"""The fast pieces never compute something else than their reference: where one cannot compute
exactly what stock TorchRL would (another layer or activation, a transform on the env, a loss
subclass, prioritised weights or loss masks), it hands over to the reference or refuses."""
import pytest
import torch
from omegaconf import OmegaConf
from torch import nn

from torchrl_esrl.collectors.es_collector import ESCollector
from torchrl_esrl.collectors.td3_collector import GymTD3Collector
from torchrl_esrl.envs import make_env, make_gym_env
from torchrl_esrl.modules.networks import flat_parameters, load_flat_parameters, make_actor, make_critic
from torchrl_esrl.modules.population import Mirrored, ModulePopulation, PopulationActor, es_population
from torchrl_esrl.objectives.td3 import TD3, ForeachSoftUpdate, ManualGradTD3Loss
from torchrl_esrl.collectors.td3_collector import make_frame_batches
from torchrl_esrl.objectives.td3 import make_td3
from torchrl_esrl.run.implementation import FAST_PIECES

FAST = {"loss_class": ManualGradTD3Loss, "target_update_class": ForeachSoftUpdate, "optimizer_impl": "fused"}  # make_td3's fast pieces


def _config(implementation="fast", **td3):
    return OmegaConf.create({
        "device": "cpu", "implementation": implementation, "seed": 0,
        "td3": {"frames_per_batch": 5, "lr": 3e-4, "gamma": 0.99, "tau": 0.005, "policy_noise": 0.2, "noise_clip": 0.5,
                "policy_delay": 2, "exploration_noise": 0.1, "loss_function": "l2", "num_threads": None, "random_frames": 0, "precision": "fp32", **td3},
    })


def _with_layer_norm(actor):
    """``actor`` with a LayerNorm after its first Linear (same parameters otherwise)."""
    mlp = actor[0].module
    mlp.insert(1, nn.LayerNorm(mlp[0].out_features))
    return actor


def _actor(env, kind: str, seed: int = 0):
    """A Hopper actor (2x32) with ``kind``: an activation of make_actor, or tanh plus a LayerNorm."""
    torch.manual_seed(seed)
    observation_dim = env.observation_spec["observation"].shape[-1]
    if kind == "layer_norm":
        return _with_layer_norm(make_actor(observation_dim, env.action_spec, (32, 32), "tanh"))
    return make_actor(observation_dim, env.action_spec, (32, 32), kind)


# ---------------------------------------------------------------------------- ES evaluation
@pytest.mark.parametrize("kind", ["elu", "layer_norm"])
def test_population_actor_refuses_what_it_cannot_compute_and_the_factory_hands_over(kind):
    actor = _actor(make_env("hopper"), kind)
    assert not PopulationActor.supports(actor)
    with pytest.raises(ValueError) as error:
        PopulationActor(actor)
    assert "\n" not in str(error.value) and "ModulePopulation" in str(error.value)
    assert es_population(actor, FAST_PIECES) is ModulePopulation


@pytest.mark.parametrize("backend", ["gym", "mujoco_batch"])
@pytest.mark.parametrize("kind", ["tanh", "relu", "elu", "layer_norm"])
def test_fast_es_evaluation_gives_the_reference_returns_over_the_first_steps(kind, backend):
    """Hopper-v5, 8 members (4 mirrored pairs, as OpenAI-ES hands them over), 6 steps each: the
    population the fast factory picks (PopulationActor for tanh/ReLU, the reference itself
    otherwise) on either backend gives the reference's actions and rewards up to float32
    rounding; the reference ModulePopulation gives, bit for bit, the actions of the actor module
    loaded with each member's parameters and stepped in gymnasium."""
    actor = _actor(make_env("hopper"), kind)
    center = flat_parameters(actor)
    offsets = 0.3 * torch.randn(4, center.numel(), generator=torch.Generator().manual_seed(1))
    params = torch.cat([center + offsets, center - offsets])
    seeds = list(range(10, 18))
    reference = ESCollector("hopper", actor, backend="gym", max_episode_steps=6, population=ModulePopulation).evaluate(params, seeds)
    population = es_population(actor, FAST_PIECES)
    assert population is (PopulationActor if kind in ("tanh", "relu") else ModulePopulation)
    fast = ESCollector("hopper", actor, backend=backend, max_episode_steps=6, population=population).evaluate(params, seeds, mirrored=Mirrored(center, offsets))
    assert reference.lengths.tolist() == fast.lengths.tolist() == [6] * 8
    torch.testing.assert_close(fast.transitions["action"], reference.transitions["action"], rtol=0, atol=1e-5)
    torch.testing.assert_close(fast.returns, reference.returns, rtol=1e-5, atol=1e-5)
    assert reference.returns.std() > 0.01  # the members act differently
    # The reference is the module itself: member 3 through load_flat_parameters and a gymnasium loop.
    module = _actor(make_env("hopper"), kind)
    load_flat_parameters(module, params[3])
    gym_env = make_gym_env("hopper", max_episode_steps=6)
    observation = gym_env.reset(seed=seeds[3])[0]
    member = reference.transitions[reference.transitions["collector", "traj_ids"] == 3]
    from tensordict import TensorDict

    for step in range(6):
        with torch.no_grad():
            action = module(TensorDict(observation=torch.as_tensor(observation, dtype=torch.float32).unsqueeze(0), batch_size=[1]))["action"][0]
        assert torch.equal(action, member["action"][step]), step
        observation = gym_env.step(action.numpy())[0]


def _dropout_actor(env, p: float = 0.2):
    """A Hopper actor with dropout after its first activation (in training mode, as built)."""
    actor = _actor(env, "tanh")
    actor[0].module.insert(2, nn.Dropout(p))
    return actor


def test_a_random_actor_never_plays_in_the_batched_physics_and_one_seed_gives_one_generation():
    """The batched physics plays members in worker threads, in an order that differs from run to
    run: an actor that draws random numbers (dropout in training mode) is refused there in one
    line, ``auto`` and the factory give the gym reference (with the reason in the pieces line),
    and the same seed gives the same generation twice. A deterministic module (ELU) still plays there."""
    from torchrl_esrl.collectors.mujoco_batch import MujocoBatchBackend
    from torchrl_esrl.collectors.es_collector import make_es_collector
    from torchrl_esrl.errors import ConfigError
    from torchrl_esrl.run.implementation import implementations

    env = make_env("hopper")
    actor = _dropout_actor(env)
    assert es_population(actor, FAST_PIECES) is ModulePopulation
    with pytest.raises(ValueError) as error:
        MujocoBatchBackend("hopper", ModulePopulation(actor), nthread=1, workers=1)
    assert "\n" not in str(error.value) and "draws random numbers" in str(error.value)
    assert ESCollector("hopper", actor, backend="auto", population=ModulePopulation).backend.name == "gym"
    with pytest.raises(ConfigError) as error:
        ESCollector("hopper", actor, backend="mujoco_batch", population=ModulePopulation)
    assert "\n" not in str(error.value) and str(error.value).startswith("es.backend: mujoco_batch cannot play this actor")
    cfg = OmegaConf.create({"implementation": "fast", "seed": 0, "env": {"id": "hopper", "max_episode_steps": 5}, "es": {"backend": "auto"}})
    collector = make_es_collector(cfg, actor)
    assert collector.backend.name == "gym"
    assert implementations(cfg, es_collector=collector)["es_physics"].startswith("reference (actor: its forward draws random numbers")
    params = flat_parameters(actor).expand(4, -1)
    generations = []
    for _ in range(2):
        torch.manual_seed(7)
        generations.append(collector.evaluate(params, [5, 5, 5, 5]))  # one actor, one start: the dropout alone tells the members apart
    assert torch.equal(generations[0].returns, generations[1].returns) and len(set(generations[0].returns.tolist())) > 1  # random, and reproduced
    deterministic = _actor(env, "elu")
    assert ESCollector("hopper", deterministic, backend="auto", population=ModulePopulation).backend.name == "mujoco_batch"


def test_each_fast_forward_refuses_a_hooked_actor_in_one_line():
    """A forward hook changes what the actor computes: the batched ES forward and the TD3 collector
    refuse it in one line naming the hook; the factories hand over to the references."""
    env = make_env("hopper", seed=0, max_episode_steps=20)
    actor = _actor(env, "tanh")
    actor[0].module.register_forward_hook(lambda module, args, output: output * 0.5)
    with pytest.raises(ValueError) as error:
        PopulationActor(actor)
    assert "\n" not in str(error.value) and "a forward hook on module.0.module" in str(error.value)
    assert es_population(actor, FAST_PIECES) is ModulePopulation
    td3 = make_td3(_config(), actor, make_critic(11, 3, (32, 32)), env.action_spec)
    with pytest.raises(ValueError) as error:
        GymTD3Collector(env, td3, 5)
    assert "\n" not in str(error.value) and "a forward hook on module.0.module" in str(error.value)
    collector, _ = make_frame_batches(_config(), env, td3)
    assert type(collector).__name__ == "Collector"
    collector.shutdown()


# ---------------------------------------------------------------------------- TD3 acting
def test_gym_td3_collector_refuses_another_transform_and_the_factory_hands_over():
    """A transform added to the TD3 env: GymTD3Collector (which reproduces make_env's transforms)
    refuses in one line; make_frame_batches hands over to TorchRL's Collector, which applies it."""
    from torchrl.envs import ObservationNorm

    env = make_env("hopper", seed=0, max_episode_steps=20)
    env.append_transform(ObservationNorm(loc=0.0, scale=2.0, in_keys=["observation"]))
    actor = _actor(env, "tanh")
    td3 = make_td3(_config(), actor, make_critic(11, 3, (32, 32)), env.action_spec)
    assert not GymTD3Collector.supports(env, td3)
    with pytest.raises(ValueError) as error:
        GymTD3Collector(env, td3, 5)
    assert "\n" not in str(error.value) and "ObservationNorm" in str(error.value)
    collector, frames = make_frame_batches(_config(), env, td3)
    assert type(collector).__name__ == "Collector"
    batch = next(frames)
    collector.shutdown()
    reference = make_env("hopper", seed=0, max_episode_steps=20).reset()["observation"]
    torch.testing.assert_close(batch["observation"][0], 2 * reference)  # ObservationNorm applied: obs * scale + loc


@pytest.mark.parametrize("kind", ["elu", "layer_norm"])
def test_gym_td3_collector_hands_an_actor_with_other_layers_to_the_collector(kind):
    env = make_env("hopper", seed=0, max_episode_steps=20)
    td3 = make_td3(_config(), _actor(env, kind), make_critic(11, 3, (32, 32)), env.action_spec)
    assert not GymTD3Collector.supports(env, td3)
    collector, _ = make_frame_batches(_config(), env, td3)
    assert type(collector).__name__ == "Collector"
    collector.shutdown()


def test_td3_in_bfloat16_says_in_one_line_that_it_is_not_for_results(capsys):
    """``td3.precision=bf16`` (docs/deviations.md, 39) is built with a one-line warning on stderr;
    float32 without one."""
    env = make_env("hopper", seed=0, max_episode_steps=20)
    make_td3(_config(), _actor(env, "tanh"), make_critic(11, 3, (32, 32)), env.action_spec)
    assert capsys.readouterr().err == ""
    td3 = make_td3(_config(precision="bf16"), _actor(env, "tanh"), make_critic(11, 3, (32, 32)), env.action_spec)
    err = capsys.readouterr().err
    assert td3.precision == "bf16" and err.count("\n") == 1 and "td3.precision=bf16" in err and "docs/deviations.md, 39" in err


# ---------------------------------------------------------------------------- TD3 update
def _batch(n=64, **extra):
    from benchmarks.common import transitions

    batch = transitions(n, 17, 6, torch.Generator().manual_seed(n))
    for key, value in extra.items():
        batch.set(key, value)
    return batch


def _td3_pair(loss_class, **kwargs):
    """(reference-seeded TD3 with ``loss_class`` and the fast pieces, the same with ManualGradTD3Loss)."""
    from torchrl.data import Bounded

    spec = Bounded(-torch.ones(6), torch.ones(6), shape=(6,))
    torch.manual_seed(0)
    actor, critic = make_actor(17, spec, (32, 32)), make_critic(17, 6, (32, 32))
    import copy

    pair = []
    for cls in (loss_class, ManualGradTD3Loss):
        torch.manual_seed(1)
        pair.append(TD3(copy.deepcopy(actor), copy.deepcopy(critic), spec, **{**FAST, "loss_class": cls}, **kwargs))
    return pair


def test_a_loss_subclass_overriding_value_loss_or_actor_loss_is_what_td3_trains():
    """TD3.update's hand-written gradients are ManualGradTD3Loss's own losses: a subclass that
    overrides value_loss or actor_loss is trained on its override, through autograd."""

    class DoubledCritic(ManualGradTD3Loss):
        def value_loss(self, tensordict):
            loss, metadata = super().value_loss(tensordict)
            return 2 * loss, metadata

    class HalvedActor(ManualGradTD3Loss):
        def actor_loss(self, tensordict):
            loss, metadata = super().actor_loss(tensordict)
            return 0.5 * loss, metadata

    batch = _batch()
    for cls, key, factor in ((DoubledCritic, "critic_loss", 2.0), (HalvedActor, "actor_loss", 0.5)):
        subclassed, plain = _td3_pair(cls)
        assert subclassed.loss.refusal(batch) is None  # the override scales the hand-written gradient through autograd
        outs = []
        for td3 in (subclassed, plain):
            torch.manual_seed(5)
            td3.update(batch)
            outs.append(td3.update(batch))
        assert outs[0][key] == pytest.approx(factor * outs[1][key], rel=1e-5)


@pytest.mark.parametrize("extra", ["priority_weight", "loss_mask"])
def test_weighted_or_masked_batches_are_handed_to_torchrl(extra):
    """Prioritised weights and TorchRL's loss masks: the hand-written gradients (a plain batch
    mean) decline, and TD3 trains on TorchRL's weighted or masked loss, as the reference does."""
    from torchrl.objectives import TD3Loss

    generator = torch.Generator().manual_seed(2)
    if extra == "priority_weight":
        batch = _batch(priority_weight=torch.rand(64, generator=generator) * 2)
    else:
        batch = _batch()
        batch.set(("collector", "mask"), torch.rand(64, generator=generator) > 0.3)
    fast, _ = _td3_pair(ManualGradTD3Loss)
    assert fast.loss.refusal() is None and fast.loss.refusal(batch) == "prioritised weights or loss mask"
    reference = _td3_pair(TD3Loss)[0]  # stock TD3Loss and autograd, the other pieces as in fast
    plain_batch = _batch()
    torch.manual_seed(5)
    unweighted = fast.loss.value_loss(plain_batch)[0].item()
    outs = []
    for td3 in (reference, fast):
        torch.manual_seed(5)
        outs.append([td3.update(batch) for _ in range(2)])
    for ref, got in zip(*outs):
        for key in ref:
            assert got[key] == pytest.approx(ref[key], rel=1e-5), key
    assert outs[0][0]["critic_loss"] != pytest.approx(unweighted, rel=1e-3)  # the weights or the mask did change the loss


# ---------------------------------------------------------------------------- the switch
def test_the_old_td3_fast_key_is_a_one_line_config_error_naming_the_new_key(run_recipe, tmp_path):
    result = run_recipe("es_td3.py", "td3.fast=false", f"hydra.run.dir={tmp_path / 'run'}", timeout=300)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr[-2000:]
    assert lines[0].startswith("config error: td3.fast: renamed to implementation"), lines


def test_the_fast_physics_under_the_reference_implementation_is_refused_before_the_run(run_recipe, tmp_path):
    """``implementation=reference es.backend=mujoco_batch`` would run the fast physics while the
    pieces line says reference: one line, exit 2, before the run directory is made."""
    run_dir = tmp_path / "run"
    result = run_recipe("es.py", "implementation=reference", "es.backend=mujoco_batch", f"hydra.run.dir={run_dir}", timeout=300)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and lines[-1].startswith("config error: es.backend: mujoco_batch"), result.stderr[-2000:]
    assert len(lines) == 1 and not run_dir.exists(), lines
