"""Spectral layer: FFT engines (torch.fft, pyfftw with bounded plan caches, pocketfft), real-to-real transforms
(DCT/DST), the box eigen-multipliers they apply, and the engine settings.

Lower layers only: nothing here imports fields, operators or solvers.
"""

from phisim.spectral.fft import (
    R2R_KINDS,
    FFTSettings,
    available_engines,
    dctn,
    dstn,
    fft_settings,
    fourier_multiply,
    get_fft_settings,
    idctn,
    idstn,
    irfftn,
    r2r_multiply,
    r2rn,
    resolve_engine,
    rfftn,
    set_fft_settings,
    wall_solve,
)

__all__ = [
    "FFTSettings", "get_fft_settings", "set_fft_settings", "fft_settings", "available_engines", "resolve_engine",
    "r2r_multiply", "wall_solve", "rfftn", "irfftn", "dctn", "idctn", "dstn", "idstn", "r2rn", "fourier_multiply",
    "R2R_KINDS",
]
