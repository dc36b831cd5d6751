"""benchmarks/adam_denormal.py: the denormal moments it times are what such a weight's Adam state
keeps under later steps; its three copies of a run's update start from the checkpoint's state, one
with its denormal moments zeroed, one flushing denormals while it runs."""
import torch

from benchmarks.adam_denormal import (SMALLEST_NORMAL, adam_moments as moments, adam_with_moments,
                                      denormal_fraction, flushing_denormals, learner_denormals, run_update_methods,
                                      zero_denormal_moments)


def test_the_denormal_moments_stay_denormal_under_adam_steps():
    adam = adam_with_moments(8)
    before = denormal_fraction(moments(adam))
    for _ in range(50):
        adam.step()
    assert 0.12 < before < 0.13
    assert denormal_fraction(moments(adam)) == before  # round-to-nearest keeps 0.9 x 4 x 2^-149 where it is
    assert denormal_fraction(moments(adam_with_moments(None))) == 0.0


def test_a_first_moment_whose_gradient_stays_zero_becomes_denormal_and_stays():
    param = torch.nn.Parameter(torch.ones(4))
    adam = torch.optim.Adam([param], lr=3e-4, fused=True)
    param.grad = torch.ones(4)
    adam.step()
    param.grad = torch.zeros(4)
    for _ in range(1200):
        adam.step()
    exp_avg = adam.state[param]["exp_avg"]
    assert bool(((exp_avg > 0) & (exp_avg < SMALLEST_NORMAL)).all())


def test_zeroing_leaves_the_normal_entries_and_flushing_holds_only_inside_the_call():
    adam = adam_with_moments(8)
    normal_before = [m[m.abs() >= SMALLEST_NORMAL].clone() for m in moments(adam)]
    zero_denormal_moments(adam)
    assert denormal_fraction(moments(adam)) == 0.0
    assert all(torch.equal(m[m.abs() >= SMALLEST_NORMAL], kept) for m, kept in zip(moments(adam), normal_before))
    denormal = torch.full((4,), 4 * 2.0 ** -149)
    seen = []
    flushing_denormals(lambda: seen.append(denormal * 1.0))()
    assert torch.equal(seen[0], torch.zeros(4))  # flushed inside
    assert torch.equal(denormal * 1.0, denormal)  # and not after


def test_the_run_update_copies_restore_the_checkpoint_and_take_steps(run_recipe, tmp_path):
    result = run_recipe("es_td3.py", "env=halfcheetah", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-2000:]
    checkpoint = sorted((tmp_path / "checkpoints").glob("checkpoint-*"))[-1]
    learners, methods = run_update_methods(checkpoint, batches=2)
    assert set(methods) == set(learners) == {"as_saved", "as_saved_flush_denormal", "denormals_zeroed"}
    saved = learners["as_saved"]
    before = saved.updates
    assert before > 0  # the run's TD3 state, not a fresh learner's
    for learner in learners.values():
        assert learner.updates == before
        assert all(torch.equal(a, b) for a, b in zip(learner.loss.parameters(), saved.loss.parameters()))
    assert learner_denormals(learners["denormals_zeroed"]) == 0
    for name, method in methods.items():
        method()
        assert learners[name].updates == before + 1  # each copy steps its own learner, once
