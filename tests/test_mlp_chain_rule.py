"""objectives/mlp_chain_rule: the hand-written MLP forward and its chain rule, against autograd."""
import pytest
import torch

from torchrl_esrl.objectives import mlp_chain_rule as chain


def test_numpy_tanh_matches_torch_tanh():
    """The hidden tanh: numpy's kernel in place without autograd (within one float32 rounding step of
    torch.tanh), torch.tanh itself where a gradient is recorded."""
    x = (3 * torch.randn(256, 256, generator=torch.Generator().manual_seed(0))).requires_grad_()
    y_torch = torch.tanh(x)
    y = chain.tanh(x)
    assert y.grad_fn is not None and y.data_ptr() != x.data_ptr()
    assert torch.equal(y, y_torch)
    with torch.no_grad():
        z = x.detach().clone()
        assert chain.tanh(z) is z
        torch.testing.assert_close(z, y_torch.detach(), rtol=0, atol=2e-7)
        assert not torch.equal(z, x)


@pytest.mark.parametrize("stacked", [False, True])
@pytest.mark.parametrize("activation", ["tanh", "relu"])
def test_backward_is_autograd_through_forward(stacked, activation):
    """forward of one network (addmm) or two stacked ones (baddbmm) and backward's parameter and input
    gradients against autograd through the same forward, float64 (no rounding to hide a wrong term);
    parameters not asked for get None."""
    generator = torch.Generator().manual_seed(0)
    sizes, lead = [7, 16, 16, 3], ((2,) if stacked else ())
    parameters = []
    for fan_in, fan_out in zip(sizes, sizes[1:]):
        parameters += [torch.randn(*lead, fan_out, fan_in, generator=generator, dtype=torch.float64).requires_grad_(),
                       torch.randn(*lead, fan_out, generator=generator, dtype=torch.float64).requires_grad_()]
    activations = [chain.ACTIVATIONS[activation]] * 2 + [None]
    x = torch.randn(*lead, 32, 7, generator=generator, dtype=torch.float64, requires_grad=True)
    out = chain.forward(chain.layers(parameters, activations), x)
    grad_out = torch.randn(out.shape, generator=generator, dtype=torch.float64)
    expected = torch.autograd.grad(out, [x, *parameters], grad_out)
    with torch.no_grad():
        inputs = []
        chain.forward(chain.layers(parameters, activations), x.detach(), inputs)
        needs = [True] * len(parameters)
        grads, grad_x = chain.backward(chain.layers(parameters, activations), inputs, grad_out, needs, input_grad=True)
        for got, want in zip([grad_x, *grads], expected):
            torch.testing.assert_close(got, want)
        needs = [False, False] + [True] * (len(parameters) - 2)  # the first layer not asked for: its gradients are None
        grads, grad_x = chain.backward(chain.layers(parameters, activations), inputs, grad_out, needs)
        assert grads[0] is None and grads[1] is None and grad_x is None
        for got, want in zip(grads[2:], expected[3:]):
            torch.testing.assert_close(got, want)
