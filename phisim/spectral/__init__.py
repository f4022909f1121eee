"""Spectral layer: FFT engines (torch.fft, pyfftw with bounded plan caches, pocketfft), real-to-real transforms
(DCT/DST), the box eigen-multipliers they apply, and the engine settings (:mod:`phisim.spectral.settings`).

The default settings are bit-reproducible: the same seed and settings give the same bits in every process,
whatever the timing (see :mod:`phisim.spectral.fft`, "Planner effort and reproducibility"); measured FFTW plans
are an opt-in (``FFTSettings(planner_effort='FFTW_MEASURE')``) that is not.

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
