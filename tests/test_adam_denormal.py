"""benchmarks/adam_denormal.py: the denormal moments it times are what such a weight's Adam state
keeps under later steps, and a checkpoint's count reads the TD3 state's float32 tensors."""
import torch

from benchmarks.adam_denormal import SMALLEST_NORMAL, adam_with_moments, denormal_fraction


def moments(adam: torch.optim.Adam) -> list[torch.Tensor]:
    return [t for state in adam.state.values() for t in (state["exp_avg"], state["exp_avg_sq"])]


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
