"""Tests of inverse.nets: parameter counts of the paper's networks, shapes, padding, errors."""

from __future__ import annotations

import pytest
import torch

from inverse.nets import MLP, UNet, count_parameters
from phisim.errors import ParameterError, ShapeError


def test_unet_parameter_counts_of_the_paper():
    assert count_parameters(UNet(1, 1, levels=4, filters=16)) == 37_697  # E3 / E4
    assert count_parameters(UNet(2, 2, levels=5, filters=16)) == 49_570  # E5


def test_unet_count_formula():
    for c_in, c_out, levels, f in [(1, 1, 1, 4), (3, 2, 3, 8), (2, 5, 6, 5)]:
        first = 9 * c_in * f + 3 * f + 9 * f * f + 3 * f
        down = 2 * (9 * f * f + 3 * f)
        up = 9 * 2 * f * f + 3 * f + 9 * f * f + 3 * f
        expected = first + (levels - 1) * (down + up) + f * c_out + c_out
        assert count_parameters(UNet(c_in, c_out, levels, f)) == expected


def test_mlp_parameter_count_of_e2():
    mlp = MLP([1, 10, 20, 10, 1], "relu")
    assert count_parameters(mlp) == 461
    assert sum(isinstance(m, torch.nn.ReLU) for m in mlp.modules()) == 3  # after hidden layers only
    assert mlp(torch.zeros(7, 1)).shape == (7, 1)


@pytest.mark.parametrize("shape", [(64, 64), (80, 60), (33, 17)])
def test_unet_shapes(shape):
    net = UNet(1, 1, levels=4, filters=4)
    out = net(torch.randn(2, 1, *shape))
    assert out.shape == (2, 1, *shape)


def test_unet_padding_modes_and_circular_equivariance():
    torch.manual_seed(0)
    net = UNet(1, 1, levels=1, filters=4, padding_mode="circular").double().eval()
    x = torch.randn(1, 1, 12, 10, dtype=torch.float64)
    shifted = net(torch.roll(x, shifts=(3, -2), dims=(2, 3)))
    torch.testing.assert_close(shifted, torch.roll(net(x), shifts=(3, -2), dims=(2, 3)))
    net0 = UNet(1, 1, levels=1, filters=4, padding_mode="zeros").double().eval()
    net0.load_state_dict(net.state_dict())
    assert not torch.allclose(net0(x), net(x))
    for mode in ("reflect", "replicate"):
        assert UNet(1, 1, 2, 4, padding_mode=mode)(torch.randn(1, 1, 8, 8)).shape == (1, 1, 8, 8)


def test_unet_is_trainable_in_float64():
    net = UNet(2, 2, levels=3, filters=4).double()
    x = torch.randn(2, 2, 16, 16, dtype=torch.float64)
    net(x).square().sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in net.parameters())


def test_net_errors():
    with pytest.raises(ParameterError):
        UNet(levels=0)
    with pytest.raises(ParameterError):
        UNet(padding_mode="periodic")
    with pytest.raises(ShapeError):
        UNet(1, 1)(torch.zeros(1, 2, 16, 16))
    with pytest.raises(ShapeError):
        UNet(1, 1, levels=4)(torch.zeros(1, 1, 4, 16))
    with pytest.raises(ParameterError):
        MLP([3])
    with pytest.raises(ParameterError):
        MLP([1, 2], "swish-ish")
    with pytest.raises(ShapeError):
        MLP([3, 2])(torch.zeros(4, 2))
