"""Operators layer: the stencils (one weighted face-flux kernel), differential operators (gradient, divergence,
laplace, curl) and transport (semi-Lagrangian, MacCormack, conservative finite volume)."""

from phisim.ops.advection import LIMITERS, SCALAR_SCHEMES, SCHEMES, advect, conservative, maccormack, semi_lagrangian
from phisim.ops.differential import curl, divergence, gradient, laplace, velocity_from_stream_function

__all__ = [
    "gradient", "divergence", "laplace", "curl", "velocity_from_stream_function",
    "advect", "semi_lagrangian", "maccormack", "conservative", "SCHEMES", "SCALAR_SCHEMES", "LIMITERS",
]
