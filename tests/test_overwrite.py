import pytest
import torch

from torchrl_esrl.envs import make_env
from torchrl_esrl.es.openes import OpenES
from torchrl_esrl.collectors.es_collector import ESCollector
from torchrl_esrl.modules.networks import flat_parameters, load_flat_parameters, make_actor
from torchrl_esrl.algorithm.overwrite import OverwriteRule


def test_decision_uses_the_average_over_the_window():
    rule = OverwriteRule(window=2, mode="hard", mix=0.5)
    assert rule(td3_return=10, es_return=0).overwrite  # 10 > 0
    decision = rule(td3_return=-30, es_return=5)  # averages: td3 -10, es 2.5
    assert not decision.overwrite
    assert decision.td3_average == -10 and decision.es_average == 2.5
    decision = rule(td3_return=40, es_return=0)  # window drops the first: td3 5, es 2.5
    assert decision.overwrite and decision.td3_average == 5
    assert [d.overwrite for d in rule.decisions] == [True, False, True]


def test_overwriting_copies_the_actor_into_the_es_mean_and_its_behaviour():
    env = make_env("swimmer")
    actor = make_actor(8, env.action_spec)
    es = OpenES(torch.zeros_like(flat_parameters(actor)), population_size=4)
    with torch.no_grad():
        for parameter in actor.parameters():
            parameter.add_(0.05 * torch.randn_like(parameter))
    es.set_mean(flat_parameters(actor), reset_optimizer=True)
    assert torch.equal(es.mean.detach(), flat_parameters(actor))
    # a copy, not a view: training the actor further leaves the mean where it was
    trained = flat_parameters(actor)
    with torch.no_grad():
        next(actor.parameters()).add_(1.0)
    assert not torch.equal(es.mean.detach(), flat_parameters(actor))
    load_flat_parameters(actor, trained)
    collector = ESCollector("swimmer", actor, backend="gym", max_episode_steps=50)
    from_mean = collector.evaluate_policy(es.mean.detach(), 2, seeds=[3, 4]).returns
    from_actor = collector.evaluate_policy(flat_parameters(actor), 2, seeds=[3, 4]).returns
    torch.testing.assert_close(from_mean, from_actor)


def test_state_round_trip():
    rule = OverwriteRule(window=3, mode="soft", mix=0.5)
    rule(1.0, 2.0)
    restored = OverwriteRule(window=1, mode="soft", mix=0.5)
    restored.load_state_dict(rule.state_dict())
    assert restored(5.0, 0.0).td3_average == rule(5.0, 0.0).td3_average == 3.0


def test_hard_mode_ignores_mix_and_soft_mode_keeps_it():
    assert OverwriteRule(window=3, mode="hard", mix=0.3).mix == 1.0
    assert OverwriteRule(window=3, mode="soft", mix=0.3).mix == 0.3
    for mode, mix in (("medium", 0.5), ("soft", 0.0), ("soft", 1.5)):
        with pytest.raises(ValueError):
            OverwriteRule(window=3, mode=mode, mix=mix)


def test_soft_overwrite_moves_the_es_mean_part_way_to_the_actor():
    """Section 5's soft overwrite on a real OpenES and a real actor: mean <- (1 - mix) mean + mix actor."""
    env = make_env("swimmer")
    actor = make_actor(8, env.action_spec)
    es = OpenES(flat_parameters(actor), population_size=4, generator=torch.Generator().manual_seed(0))
    es.tell(es.ask(), torch.tensor([1.0, 4.0, 2.0, 3.0]))  # one real ES step: Adam has moments to clear
    old_mean = es.mean.detach().clone()
    with torch.no_grad():
        for parameter in actor.parameters():
            parameter.add_(0.05 * torch.randn_like(parameter))
    rule = OverwriteRule(window=1, mode="soft", mix=0.25)
    assert rule(td3_return=10.0, es_return=0.0).overwrite
    es.set_mean(flat_parameters(actor), reset_optimizer=True, mix=rule.mix)
    torch.testing.assert_close(es.mean.detach(), 0.75 * old_mean + 0.25 * flat_parameters(actor))
    assert not es.optimizer.state  # Adam restarted
    # the distance to the actor shrinks by exactly (1 - mix)
    before, after = (old_mean - flat_parameters(actor)).norm(), (es.mean.detach() - flat_parameters(actor)).norm()
    assert after == pytest.approx(0.75 * before.item(), rel=1e-4)


@pytest.mark.parametrize(("mode", "mix"), [("hard", 1.0), ("soft", 0.5)])
def test_the_returned_policys_return_is_the_es_means_after_the_rule(mode, mix):
    """Kept: the ES evaluation; overwritten: the TD3 actor's (hard, the mean is that actor) or a new
    evaluation of the mixed mean (soft), asked for only then."""
    rule, asked = OverwriteRule(window=1, mode=mode, mix=mix), []

    def evaluate_mean():
        asked.append(True)
        return 7.0

    assert rule.mean_return(rule(td3_return=1.0, es_return=2.0), evaluate_mean) == 2.0 and not asked
    overwritten = rule.mean_return(rule(td3_return=5.0, es_return=3.0), evaluate_mean)
    assert overwritten == (5.0 if mode == "hard" else 7.0) and len(asked) == (mode == "soft")
