"""Networks of the reference experiments: a configurable 2-D U-net and a fully connected MLP.

U-net (Ronneberger et al. 2015, in the variant of the physical-gradient paper, appendix B.2): ``levels``
resolution levels; at every level a block of two ``conv3×3 → BatchNorm → ReLU`` layers with ``filters``
channels; max-pooling (2×2) down, bilinear upsampling (×2) up, concatenation with the skip connection
of the same level, then the block again; a final ``1×1`` convolution to ``out_channels``. With
``levels`` levels there are ``levels − 1`` poolings.

Parameter counts (convolutions with bias, BatchNorm with affine weight and bias)::

    first block   9·c_in·f + f + 2f  +  9·f² + f + 2f
    per down level    2·(9f² + 3f)                     (levels − 1 of them)
    per up level      9·2f·f + 3f + 9f² + 3f          (levels − 1; the first conv sees 2f channels)
    output            f·c_out + c_out

For ``levels=4, filters=16, in 1, out 1`` this is 2,544 + 3·4,704 + 3·7,008 + 17 = **37,697** (E3/E4);
for ``levels=5, filters=16, in 2, out 2`` it is 2,688 + 4·4,704 + 4·7,008 + 34 = **49,570** (E5).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from phisim.checks import check_choice, check_int
from phisim.errors import ParameterError, ShapeError

__all__ = ["UNet", "MLP", "count_parameters"]

_PADDING_MODES = ("zeros", "circular", "reflect", "replicate")
_ACTIVATIONS = {"relu": nn.ReLU, "tanh": nn.Tanh, "sigmoid": nn.Sigmoid, "gelu": nn.GELU, "elu": nn.ELU,
                "softplus": nn.Softplus, "silu": nn.SiLU}


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters of ``module``.

    Args:
        module: Any torch module.

    Returns:
        The sum of ``p.numel()`` over parameters with ``requires_grad``.
    """
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


class _Block(nn.Sequential):
    """Two ``conv3×3 → BatchNorm → ReLU`` layers."""

    def __init__(self, c_in: int, c_out: int, padding_mode: str):
        super().__init__(
            nn.Conv2d(c_in, c_out, 3, padding=1, padding_mode=padding_mode),
            nn.BatchNorm2d(c_out),
            nn.ReLU(inplace=True),
            nn.Conv2d(c_out, c_out, 3, padding=1, padding_mode=padding_mode),
            nn.BatchNorm2d(c_out),
            nn.ReLU(inplace=True),
        )


class UNet(nn.Module):
    """Configurable 2-D U-net (see the module docstring for the architecture and parameter counts).

    Input ``(B, in_channels, X, Y)``, output ``(B, out_channels, X, Y)``. Any ``X, Y ≥ 2^(levels−1)``
    work: pooling floors odd sizes and the upsampling interpolates to the skip connection's exact size.
    Upsampling is bilinear with ``align_corners=False``.

    Args:
        in_channels: Input channels.
        out_channels: Output channels.
        levels: Resolution levels (≥ 1); ``levels − 1`` poolings.
        filters: Channels of every convolution (except the output).
        padding_mode: ``"zeros"``, ``"circular"`` (periodic domains; the reference code's choice),
            ``"reflect"`` or ``"replicate"``.

    Raises:
        ParameterError: Non-positive sizes or an unknown padding mode.
    """

    def __init__(
        self,
        in_channels: int = 1,
        out_channels: int = 1,
        levels: int = 4,
        filters: int = 16,
        padding_mode: str = "circular",
    ):
        super().__init__()
        # sizes beyond 2**31 - 1 cannot allocate a layer (and levels beyond 31 cannot pool a grid torch holds)
        self.in_channels = check_int(in_channels, "in_channels", minimum=1, maximum=2**31 - 1)
        self.out_channels = check_int(out_channels, "out_channels", minimum=1, maximum=2**31 - 1)
        self.levels = check_int(levels, "levels", minimum=1, maximum=31)
        self.filters = check_int(filters, "filters", minimum=1, maximum=2**31 - 1)
        self.padding_mode = check_choice(padding_mode, "padding_mode", _PADDING_MODES)
        f = self.filters
        self.down = nn.ModuleList(
            [_Block(self.in_channels if i == 0 else f, f, padding_mode) for i in range(self.levels)]
        )
        self.up = nn.ModuleList([_Block(2 * f, f, padding_mode) for _ in range(self.levels - 1)])
        self.out = nn.Conv2d(f, self.out_channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Applies the network.

        Args:
            x: ``(B, in_channels, X, Y)``.

        Returns:
            ``(B, out_channels, X, Y)``.

        Raises:
            ShapeError: Wrong number of dimensions or channels, or a grid too small for the levels.
        """
        if x.ndim != 4 or x.shape[1] != self.in_channels:
            raise ShapeError(
                f"UNet expects (B, {self.in_channels}, X, Y), got {tuple(x.shape)}; add a channel axis with "
                "x.unsqueeze(1) for scalar fields"
            )
        min_size = 2 ** (self.levels - 1)
        if min(x.shape[-2:]) < min_size:
            raise ShapeError(
                f"grid {tuple(x.shape[-2:])} too small for {self.levels} levels (need >= {min_size})"
            )
        skips = []
        h = x
        for i, block in enumerate(self.down):
            if i > 0:
                h = F.max_pool2d(h, 2)
            h = block(h)
            skips.append(h)
        for block, skip in zip(self.up, reversed(skips[:-1])):
            h = F.interpolate(h, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            h = block(torch.cat([h, skip], dim=1))
        return self.out(h)


class MLP(nn.Module):
    """Fully connected network ``sizes[0] → … → sizes[-1]`` with bias, activation after hidden layers.

    E2 uses ``MLP([1, 10, 20, 10, 1], "relu")``: 461 parameters.

    Args:
        sizes: Layer widths, at least two entries.
        activation: Name (``relu``, ``tanh``, ``sigmoid``, ``gelu``, ``elu``, ``softplus``, ``silu``) or a
            module class / factory applied after every hidden layer (not after the output layer).

    Raises:
        ParameterError: Fewer than two sizes, a non-positive size, or an unknown activation name.
    """

    def __init__(self, sizes: Sequence[int], activation: str | type[nn.Module] = "relu"):
        super().__init__()
        if isinstance(sizes, (str, bytes)) or not isinstance(sizes, Sequence) or len(sizes) < 2:
            raise ParameterError(f"sizes must be a sequence of at least two positive widths, got {sizes!r}")
        sizes = [check_int(s, f"sizes[{i}]", minimum=1, maximum=2**31 - 1) for i, s in enumerate(sizes)]
        if isinstance(activation, str):
            if activation not in _ACTIVATIONS:
                raise ParameterError(f"unknown activation {activation!r}; known: {sorted(_ACTIVATIONS)}")
            act = _ACTIVATIONS[activation]
        elif callable(activation):
            act = activation
        else:
            raise ParameterError(f"activation must be a name {sorted(_ACTIVATIONS)} or a module class/factory, "
                                 f"got {activation!r}")
        layers: list[nn.Module] = []
        for i in range(len(sizes) - 1):
            layers.append(nn.Linear(sizes[i], sizes[i + 1]))
            if i < len(sizes) - 2:
                layers.append(act())
        self.net = nn.Sequential(*layers)
        self.sizes = sizes

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Applies the network.

        Args:
            x: ``(B, sizes[0])``.

        Returns:
            ``(B, sizes[-1])``.

        Raises:
            ShapeError: The last axis is not ``sizes[0]``.
        """
        if x.ndim < 1 or x.shape[-1] != self.sizes[0]:
            raise ShapeError(f"MLP expects (..., {self.sizes[0]}), got {tuple(x.shape)}")
        return self.net(x)
