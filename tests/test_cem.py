"""CEM-RL's diagonal CEM update (Pourchot and Sigaud 2019), its TD3 member step and its config section."""
import math

import pytest
import torch
from conftest import ROOT
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from torchrl_esrl.errors import ConfigError
from torchrl_esrl.es.cem import CEMConfig, DiagonalCEM, elite_weights
from torchrl_esrl.run.config import validate_config


def test_elite_weights_are_log_rank_weights_summing_to_one():
    w = elite_weights(5)
    expected = torch.tensor([math.log(6 / i) for i in range(1, 6)])
    assert torch.allclose(w, expected / expected.sum())
    assert torch.all(w[:-1] > w[1:])  # better rank, larger weight


def test_tell_is_the_reference_sepcem_update_on_hand_computed_numbers():
    cem = DiagonalCEM(torch.zeros(3), population_size=4, sigma_init=0.1, damping_init=1e-3, damping_end=1e-5, damping_tau=0.5)
    assert torch.allclose(cem.var, torch.full((3,), 0.1))  # sigma_init is a variance, as in the reference
    population = torch.tensor([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [3.0, 1.0, 0.0], [4.0, 0.0, 2.0]])
    returns = torch.tensor([10.0, -5.0, 30.0, 0.0])  # parents: member 2 (best), then member 0
    elites = cem.tell(population, returns)
    assert elites.tolist() == [2, 0]
    # weights log(3), log(1.5) normalised: 0.730423, 0.269577
    # damping decayed BEFORE use: 0.5 * 1e-3 + 0.5 * 1e-5 = 5.05e-4
    # mean = 0.730423 * [3, 1, 0] + 0.269577 * [1, 0, 0]                       = [2.460845, 0.730423, 0]
    # var  = 1/2 * (0.730423 * [9, 1, 0] + 0.269577 * [1, 0, 0]) + 5.05e-4      = [3.422196, 0.365716, 5.05e-4]
    assert torch.allclose(cem.mean, torch.tensor([2.460845, 0.730423, 0.0]), atol=1e-5)
    assert torch.allclose(cem.var, torch.tensor([3.422196, 0.365716, 5.05e-4]), atol=1e-5)
    assert cem.damping == pytest.approx(5.05e-4)
    # the losers (members 1 and 3) moved nothing: coordinate 2 is non-zero only in member 3


def test_ask_is_antithetic_for_an_even_population():
    cem = DiagonalCEM(torch.full((5,), 1.0), population_size=6, sigma_init=0.04, generator=torch.Generator().manual_seed(2))
    samples = cem.ask()
    assert torch.allclose(samples[:3] - 1.0, -(samples[3:] - 1.0))
    odd = DiagonalCEM(torch.zeros(5), population_size=5, sigma_init=0.04)
    assert not odd.antithetic and odd.ask().shape == (5, 5)


def test_ask_samples_the_diagonal_gaussian():
    cem = DiagonalCEM(torch.full((2,), 5.0), population_size=4000, sigma_init=0.25, generator=torch.Generator().manual_seed(1))
    cem.var = torch.tensor([0.25, 4.0])
    samples = cem.ask()
    assert samples.shape == (4000, 2)
    assert torch.allclose(samples.mean(0), torch.tensor([5.0, 5.0]), atol=0.1)
    assert torch.allclose(samples.std(0), torch.tensor([0.5, 2.0]), rtol=0.05)


def test_cem_climbs_a_quadratic():
    target = torch.linspace(-1, 1, 8)
    cem = DiagonalCEM(torch.zeros(8), population_size=20, sigma_init=0.25, damping_init=1e-2, generator=torch.Generator().manual_seed(0))
    start = (cem.mean - target).norm()
    for _ in range(60):
        population = cem.ask()
        cem.tell(population, -((population - target) ** 2).sum(1))
    assert (cem.mean - target).norm() < 0.1 * start


def test_gradient_steps_follow_the_reference_schedule():
    """Per RL member: loaded into the actor with a fresh Adam, F // members critic steps, then
    F actor steps (reference es_grad.py); the other members are left as sampled."""
    from torchrl_esrl.collectors.es_collector import ESCollector
    from torchrl_esrl.data.multibuffer import MultiBuffer
    from torchrl_esrl.envs import make_env
    from torchrl_esrl.es.cem import cem_rl_gradient_steps
    from torchrl_esrl.modules.networks import flat_parameters, make_actor, make_critic
    from torchrl_esrl.objectives.td3 import TD3

    env = make_env("swimmer", max_episode_steps=40)
    actor = make_actor(8, env.action_spec, (16, 16))
    td3 = TD3(actor, make_critic(8, 2, (16, 16)), env.action_spec)
    cem = DiagonalCEM(flat_parameters(actor), population_size=4, sigma_init=1e-3, generator=torch.Generator().manual_seed(0))
    population = cem.ask()
    generation = ESCollector("swimmer", actor, backend="gym", max_episode_steps=40).evaluate(population)
    buffer = MultiBuffer(ratio=(0, 0, 1), capacity=1000, batch_size=8, min_size=8)
    buffer.extend(generation.transitions, "noisy")
    frames = generation.frames  # F: 4 members x 40 steps
    assert frames == 160
    sampled = population.clone()
    critic_adam_steps = lambda: {int(v["step"]) for v in td3.critic_optimizer.state.values()}  # noqa: E731

    steps = cem_rl_gradient_steps(td3, buffer, population, rl_members=2, frames=frames, tau=0.005)
    assert steps["critic_steps"] == 2 * (160 // 2) and steps["actor_steps"] == 2 * 160
    assert critic_adam_steps() == {160}  # the critic (and its Adam) is shared across members
    # fresh Adam per member: the last member's actor optimiser counted its own F steps only
    assert {int(v["step"]) for v in td3.actor_optimizer.state.values()} == {160}
    assert not torch.equal(population[0], sampled[0]) and not torch.equal(population[1], sampled[1])
    assert torch.equal(population[2:], sampled[2:])
    assert torch.equal(population[1], flat_parameters(actor))


class _Stop(Exception):
    pass


def test_gradient_steps_stopped_anywhere_continue_from_their_position_to_the_same_population_and_critic():
    """A stop between two steps (the run's stop point: ``on_step``) leaves a :class:`GradientStepsPosition`
    from which the same call continues, mid-member too, to the population, critic, step counts and
    losses of the steps taken without a stop. (tests/test_lifecycle.py stops a run there, checkpoints,
    and resumes it in a new process.)"""
    from torchrl_esrl.collectors.es_collector import ESCollector
    from torchrl_esrl.data.multibuffer import MultiBuffer
    from torchrl_esrl.envs import make_env
    from torchrl_esrl.es.cem import GradientStepsPosition, cem_rl_gradient_steps
    from torchrl_esrl.modules.networks import flat_parameters, make_actor, make_critic
    from torchrl_esrl.objectives.td3 import TD3

    env = make_env("swimmer", max_episode_steps=20)

    def setup():
        torch.manual_seed(0)
        actor = make_actor(8, env.action_spec, (16, 16))
        td3 = TD3(actor, make_critic(8, 2, (16, 16)), env.action_spec)
        cem = DiagonalCEM(flat_parameters(actor), population_size=4, sigma_init=1e-3, generator=torch.Generator().manual_seed(0))
        population = cem.ask()
        buffer = MultiBuffer(ratio=(0, 0, 1), capacity=1000, batch_size=8, min_size=8)
        buffer.extend(ESCollector("swimmer", actor, backend="gym", max_episode_steps=20).evaluate(population).transitions, "noisy")
        torch.manual_seed(1)  # the batches' draws
        return td3, buffer, population

    frames = 40  # per member of 2: 20 critic steps (1-20, 61-80), then 40 actor steps (21-60, 81-120)
    td3, buffer, population = setup()
    whole = cem_rl_gradient_steps(td3, buffer, population, rl_members=2, frames=frames, tau=0.005)
    for stops in ([1], [20, 61], [60, 100, 120], [35, 36, 79]):
        stopped, buffer_, population_ = setup()
        at, taken = GradientStepsPosition(), {"steps": 0}

        def on_step():
            taken["steps"] += 1
            if taken["steps"] in stops:
                raise _Stop

        for _ in stops:
            with pytest.raises(_Stop):
                cem_rl_gradient_steps(stopped, buffer_, population_, 2, frames, 0.005, at, on_step)
        steps = cem_rl_gradient_steps(stopped, buffer_, population_, 2, frames, 0.005, at, on_step)
        assert taken["steps"] == 120 and steps == whole, stops
        assert torch.equal(population_, population), stops
        for mine, theirs in zip(stopped.loss.qvalue_network_params.values(True, True), td3.loss.qvalue_network_params.values(True, True)):
            assert torch.equal(mine, theirs), stops
        assert stopped.updates == td3.updates


def test_gradient_steps_are_td3s_own_steps_bit_for_bit_and_take_its_backward_override():
    """CEM-RL's gradient steps are :meth:`TD3.gradient_step`: with make_td3's fast pieces they give
    bit for bit the population and critic of the plain sequence (loss, ``loss.backward()``, Adam's
    ``step()``, the soft update), and a TD3 subclass's ``backward`` (gradient clipping) acts on every step,
    run on ``td3.num_threads`` threads."""
    import copy

    from torchrl_esrl.collectors.es_collector import ESCollector
    from torchrl_esrl.data.multibuffer import MultiBuffer
    from torchrl_esrl.envs import make_env
    from torchrl_esrl.es.cem import cem_rl_gradient_steps, load_actor_and_target
    from torchrl_esrl.modules.networks import flat_parameters, make_actor, make_critic
    from torchrl_esrl.objectives.td3 import TD3, ForeachSoftUpdate, ManualGradTD3Loss

    class ClippedTD3(TD3):
        calls = 0
        threads = set()

        def backward(self, loss, optimizer):
            super().backward(loss, optimizer)
            torch.nn.utils.clip_grad_norm_(optimizer.param_groups[0]["params"], 1e-3)
            ClippedTD3.calls += 1
            ClippedTD3.threads.add(torch.get_num_threads())

    env = make_env("swimmer", max_episode_steps=30)
    fast = {"loss_class": ManualGradTD3Loss, "target_update_class": ForeachSoftUpdate, "optimizer_impl": "fused"}

    def learner(td3_class=TD3):
        torch.manual_seed(0)
        return td3_class(make_actor(8, env.action_spec, (16, 16)), make_critic(8, 2, (16, 16)), env.action_spec, **fast)

    td3 = learner()
    cem = DiagonalCEM(flat_parameters(td3.actor), population_size=4, sigma_init=1e-2, generator=torch.Generator().manual_seed(0))
    population = cem.ask()
    generation = ESCollector("swimmer", td3.actor, backend="gym", max_episode_steps=30).evaluate(population)
    buffer = MultiBuffer(ratio=(0, 0, 1), capacity=1000, batch_size=8, min_size=8)
    buffer.extend(generation.transitions, "noisy")
    frames, members, tau = 40, 2, 0.005

    sampled = population.clone()
    plain, plain_population = learner(), population.clone()
    torch.manual_seed(1)
    for member in range(members):  # the plain sequence, step by step
        load_actor_and_target(plain, plain_population[member])
        loss = plain.loss
        for steps, loss_fn, optimizer, target, source in (
            (frames // members, loss.value_loss, plain.critic_optimizer, loss.target_qvalue_network_params, loss.qvalue_network_params),
            (frames, loss.actor_loss, plain.actor_optimizer, loss.target_actor_network_params, loss.actor_network_params),
        ):
            for _ in range(steps):
                value, _ = loss_fn(buffer.sample())
                optimizer.zero_grad(set_to_none=True)
                value.backward()
                optimizer.step()
                with torch.no_grad():
                    target.data.lerp_(source.data, tau)
        plain_population[member] = flat_parameters(plain.actor)

    torch.manual_seed(1)
    cem_rl_gradient_steps(td3, buffer, population, members, frames, tau)
    assert torch.equal(population, plain_population) and not torch.equal(population[0], cem.mean)
    for name in ("qvalue_network_params", "target_qvalue_network_params", "target_actor_network_params"):  # the critics and both targets
        ours, theirs = getattr(td3.loss, name), getattr(plain.loss, name)
        assert all(torch.equal(ours.get(key), theirs.get(key)) for key in theirs.keys(True, True)), name

    clipped, clipped_population = learner(ClippedTD3), sampled.clone()
    clipped.num_threads, caller_threads = 1, torch.get_num_threads()  # a job's share of the cores, as td3.num_threads sets it
    torch.set_num_threads(3)
    torch.manual_seed(1)
    try:
        steps = cem_rl_gradient_steps(clipped, buffer, clipped_population, members, frames, tau)
        assert torch.get_num_threads() == 3  # the caller's count, restored
    finally:
        torch.set_num_threads(caller_threads)
    assert ClippedTD3.calls == steps["critic_steps"] + steps["actor_steps"] == members * (frames // members) + members * frames
    assert ClippedTD3.threads == {1}  # every step on TD3's thread count, as its own phase runs
    for member in range(members):  # trained, and differently from the unclipped steps
        assert not torch.equal(clipped_population[member], sampled[member])
        assert not torch.equal(clipped_population[member], population[member])


def test_cem_has_the_ask_tell_interface_and_the_es_phase_runs_it():
    """The ES phase of Algorithm 1 takes any strategy with the ask/tell interface: two CEM
    generations on Swimmer, every transition routed, the mean moved, the generation counted."""
    from torchrl_esrl.algorithm.es_phase import es_phase
    from torchrl_esrl.collectors.es_collector import ESCollector
    from torchrl_esrl.data.multibuffer import MultiBuffer
    from torchrl_esrl.data.threshold import Threshold
    from torchrl_esrl.envs import make_env
    from torchrl_esrl.es.strategy import EvolutionStrategy
    from torchrl_esrl.modules.networks import flat_parameters, make_actor

    actor = make_actor(8, make_env("swimmer").action_spec, (16, 16))
    cem = DiagonalCEM(flat_parameters(actor), population_size=4, sigma_init=1e-2, generator=torch.Generator().manual_seed(0))
    assert isinstance(cem, EvolutionStrategy)
    collector = ESCollector("swimmer", actor, backend="gym", max_episode_steps=30, seed=3)
    buffer = MultiBuffer(ratio=(0.5, 0.5, 0.0), capacity=1000, batch_size=8, min_size=8)
    before = cem.mean.clone()
    returns = es_phase(cem, collector, buffer, Threshold(0.9), generations=2)
    assert len(returns) == 2 and cem.generation == 2
    sizes = buffer.sizes()
    assert sizes["good"] + sizes["bad"] == 2 * 4 * 30 and sizes["noisy"] == 0
    assert not torch.equal(cem.mean, before)


def test_cem_set_mean_and_non_finite_returns():
    cem = DiagonalCEM(torch.zeros(3), population_size=4, sigma_init=0.1, generator=torch.Generator().manual_seed(0))
    var = cem.var.clone()
    cem.set_mean(torch.full((3,), 4.0), mix=0.25)
    assert torch.allclose(cem.mean, torch.full((3,), 1.0)) and torch.equal(cem.var, var)
    cem.set_mean(torch.full((3,), 2.0), reset_optimizer=True)
    assert torch.equal(cem.mean, torch.full((3,), 2.0))
    population = cem.ask()
    assert cem.mirrored(population) is None  # CEM-RL's members are evaluated row by row
    with pytest.raises(FloatingPointError, match="non-finite"):
        cem.tell(population, torch.tensor([1.0, float("nan"), 0.0, 2.0]))
    assert cem.generation == 0 and torch.equal(cem.mean, torch.full((3,), 2.0))


def test_the_cem_section_refuses_an_odd_antithetic_population_in_one_line_as_the_reference_asserts():
    """sepCEM asserts an even population with antithetic sampling (the authors' ``ES.py``); the
    section's own check says so before any work, naming the key, instead of sampling without pairs."""
    CEMConfig.check(OmegaConf.structured(CEMConfig), "cem")  # the defaults: 10, antithetic
    CEMConfig.check(OmegaConf.structured(CEMConfig(population_size=5, antithetic=False)), "cem")
    with pytest.raises(ConfigError) as error:
        CEMConfig.check(OmegaConf.structured(CEMConfig(population_size=5)), "cem")
    assert str(error.value) == "cem.population_size: 5 is invalid with cem.antithetic=true (allowed: an even integer >= 2)"
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):  # a recipe's config: validate_config runs the section's check
        cfg = compose("cem_rl", overrides=["cem.population_size=5"])
    with pytest.raises(ConfigError, match=r"^cem\.population_size: 5 is invalid with cem\.antithetic=true"):
        validate_config(cfg)
