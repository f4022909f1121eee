"""Spectral grids for the ETDRK steppers: real FFT on periodic axes, sine/cosine transforms on wall axes.

Grid convention (one for all three kinds of axis, so that a field keeps its shape whatever the boundaries):
an axis of length ``L`` with ``N`` samples holds the points

* periodic: ``x_j = j L / N`` (``j = 0 .. N-1``); modes ``exp(i k x)`` with ``k = 2 pi m / L``,
  ``m = 0, 1, .., -1`` (``torch.fft.fftfreq``; the axis transformed last uses the half spectrum of ``rfft``).
* ``"dirichlet"`` (sine basis, DST-II/DST-III) and ``"neumann"`` (cosine basis, DCT-II/DCT-III): the cell
  centres ``x_j = (j + 1/2) L / N`` with the walls at ``x = 0`` and ``x = L`` half a spacing outside the
  first and last sample. Modes ``sin(k x)`` with ``k = pi m / L``, ``m = 1 .. N`` (Dirichlet: the field and all
  its even derivatives vanish on the walls) or ``cos(k x)`` with ``m = 0 .. N-1`` (Neumann: all odd derivatives
  vanish on the walls).

Every transform is built from ``torch.fft.rfft``/``irfft`` of an extended array and elementwise twiddle factors
that are precomputed on construction, so the transforms are differentiable, run on any device and trace into
``torch.compile(fullgraph=True)`` graphs (no host synchronisation, no branches on values).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from phisim.errors import BoundaryError, ParameterError, ShapeError

__all__ = ["SpectralGrid", "BOUNDARIES", "dct2", "idct2", "dst2", "idst2"]

#: The axis kinds a :class:`SpectralGrid` understands.
BOUNDARIES = ("periodic", "dirichlet", "neumann")


def _twiddle(n: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``exp(-i pi m / (2 n))`` for ``m = 0 .. n`` (complex, in the complex type matching ``dtype``)."""
    m = torch.arange(n + 1, dtype=torch.float64)
    w = torch.polar(torch.ones_like(m), -math.pi * m / (2 * n))
    return w.to(device=device, dtype=torch.complex128 if dtype == torch.float64 else torch.complex64)


def dct2(x: torch.Tensor, twiddle: torch.Tensor | None = None) -> torch.Tensor:
    """Unnormalised DCT-II along the last axis: ``X_m = sum_j x_j cos(pi m (2 j + 1) / (2 N))``.

    Computed as the ``rfft`` of the even extension ``[x, flip(x)]`` (length ``2N``) times a phase.

    Args:
        x: Real tensor, transformed along its last axis.
        twiddle: Optional precomputed ``exp(-i pi m / (2N))``, ``m = 0..N`` (see :class:`SpectralGrid`).

    Returns:
        Real tensor of the same shape.
    """
    n = x.shape[-1]
    if twiddle is None:
        twiddle = _twiddle(n, x.dtype, x.device)
    y = torch.fft.rfft(torch.cat([x, x.flip(-1)], dim=-1), dim=-1)
    return 0.5 * (y[..., :n] * twiddle[:n]).real


def idct2(c: torch.Tensor, twiddle: torch.Tensor | None = None) -> torch.Tensor:
    """Inverse of :func:`dct2` (a DCT-III scaled by ``1/N``).

    Args:
        c: Real DCT-II coefficients along the last axis.
        twiddle: Optional precomputed ``exp(-i pi m / (2N))``, ``m = 0..N``.

    Returns:
        The real samples ``x`` with ``dct2(x) == c``.
    """
    n = c.shape[-1]
    if twiddle is None:
        twiddle = _twiddle(n, c.dtype, c.device)
    z = c * twiddle[:n].conj()
    z = torch.cat([z, torch.zeros_like(z[..., :1])], dim=-1)
    return torch.fft.irfft(z, n=2 * n, dim=-1)[..., :n] * 2.0


def dst2(x: torch.Tensor, twiddle: torch.Tensor | None = None, sign: torch.Tensor | None = None) -> torch.Tensor:
    """Unnormalised DST-II along the last axis: ``X_m = sum_j x_j sin(pi (m + 1) (2 j + 1) / (2 N))``.

    Uses ``DST-II(x)_m = DCT-II((-1)^j x_j)_{N-1-m}``.

    Args:
        x: Real tensor, transformed along its last axis.
        twiddle: Optional precomputed twiddle factors (as for :func:`dct2`).
        sign: Optional precomputed ``(-1)^j``.

    Returns:
        Real tensor of the same shape; entry ``m`` belongs to the mode ``sin(pi (m + 1) x / L)``.
    """
    if sign is None:
        sign = _alternating(x.shape[-1], x.dtype, x.device)
    return dct2(x * sign, twiddle).flip(-1)


def idst2(c: torch.Tensor, twiddle: torch.Tensor | None = None, sign: torch.Tensor | None = None) -> torch.Tensor:
    """Inverse of :func:`dst2`.

    Args:
        c: Real DST-II coefficients along the last axis.
        twiddle: Optional precomputed twiddle factors.
        sign: Optional precomputed ``(-1)^j``.

    Returns:
        The real samples ``x`` with ``dst2(x) == c``.
    """
    if sign is None:
        sign = _alternating(c.shape[-1], c.dtype, c.device)
    return idct2(c.flip(-1), twiddle) * sign


def _alternating(n: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    return (1.0 - 2.0 * (torch.arange(n) % 2)).to(dtype=dtype, device=device)


def _as_tuple(value, ndim: int, name: str) -> tuple:
    if isinstance(value, (list, tuple)):
        if len(value) != ndim:
            raise ShapeError(f"{name} has {len(value)} entries but the grid has {ndim} axes")
        return tuple(value)
    return (value,) * ndim


class SpectralGrid:
    """A rectangular 1-D/2-D/3-D grid with a spectral basis per axis (periodic, sine or cosine).

    The grid owns the forward/inverse transforms (physical samples <-> spectral coefficients), the wavenumber
    tensors from which linear operators are built, and the dealiasing mask. Transform buffers live on the grid's
    device in its dtype.

    Args:
        domain: Length of each axis (a number for all axes or one per axis), ``> 0``.
        resolution: Samples per axis (an int for all axes or one per axis), ``>= 2``.
        ndim: Number of spatial axes (1, 2 or 3); taken from ``domain``/``resolution`` when those are sequences.
        boundaries: ``"periodic"``, ``"dirichlet"`` or ``"neumann"``, one for all axes or one per axis.
        dtype: ``torch.float32`` or ``torch.float64`` (the dtype of physical fields).
        device: Torch device of all buffers.

    Attributes:
        ndim: Number of spatial axes.
        domain: Axis lengths.
        resolution: Samples per axis.
        boundaries: Axis kinds.
        spectral_shape: Shape of the spectral coefficients of one channel.
        spectral_is_complex: Whether the coefficients are complex (some axis is periodic).
        wavenumbers: One float64 tensor per axis, broadcastable to ``spectral_shape`` (``k = 2 pi m / L`` on
            periodic axes, ``pi m / L`` on wall axes).

    Raises:
        ParameterError: Non-positive or non-finite domain, resolution below 2, unsupported dtype or ndim.
        BoundaryError: Unknown axis kind.
    """

    def __init__(self, domain: float | Sequence[float] = 1.0, resolution: int | Sequence[int] = 64,
                 ndim: int | None = None, boundaries: str | Sequence[str] = "periodic",
                 dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"):
        if ndim is None:
            ndim = next((len(v) for v in (domain, resolution, boundaries) if isinstance(v, (list, tuple))), 1)
        if not isinstance(ndim, int) or ndim not in (1, 2, 3):
            raise ParameterError(f"ndim must be 1, 2 or 3, got {ndim!r}")
        self.ndim = ndim
        dom = _as_tuple(domain, ndim, "domain")
        res = _as_tuple(resolution, ndim, "resolution")
        bnd = _as_tuple(boundaries, ndim, "boundaries")
        for d in dom:
            try:
                ok = math.isfinite(float(d)) and float(d) > 0
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise ParameterError(f"every domain length must be a finite number > 0, got {domain!r}")
        for n in res:
            if isinstance(n, bool) or not isinstance(n, int) or n < 2:
                raise ParameterError(f"every resolution must be an int >= 2, got {resolution!r}")
        for b in bnd:
            if b not in BOUNDARIES:
                raise BoundaryError(f"unknown boundary {b!r}; expected one of {BOUNDARIES}")
        if dtype not in (torch.float32, torch.float64):
            raise ParameterError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        self.domain = tuple(float(d) for d in dom)
        self.resolution = tuple(res)
        self.boundaries = tuple(bnd)
        self.dtype = dtype
        self.device = torch.device(device)
        self.complex_dtype = torch.complex128 if dtype == torch.float64 else torch.complex64
        self.periodic_axes = tuple(i for i, b in enumerate(bnd) if b == "periodic")
        self.wall_axes = tuple(i for i, b in enumerate(bnd) if b != "periodic")
        self.spectral_is_complex = bool(self.periodic_axes)
        shape = list(res)
        if self.periodic_axes:
            last = self.periodic_axes[-1]
            shape[last] = res[last] // 2 + 1
        self.spectral_shape = tuple(shape)
        self._twiddles = {a: _twiddle(res[a], dtype, self.device) for a in self.wall_axes}
        self._signs = {a: _alternating(res[a], dtype, self.device) for a in self.wall_axes
                       if bnd[a] == "dirichlet"}
        ks = []
        modes = []
        for a in range(ndim):
            n, length = res[a], self.domain[a]
            if bnd[a] == "periodic":
                if self.periodic_axes and a == self.periodic_axes[-1]:
                    m = torch.arange(n // 2 + 1, dtype=torch.float64)
                else:
                    m = torch.fft.fftfreq(n, d=1.0 / n, dtype=torch.float64)
                k = 2 * math.pi * m / length
                mmax = n // 2
            elif bnd[a] == "dirichlet":
                m = torch.arange(1, n + 1, dtype=torch.float64)
                k = math.pi * m / length
                mmax = n
            else:
                m = torch.arange(n, dtype=torch.float64)
                k = math.pi * m / length
                mmax = n
            view = [1] * ndim
            view[a] = -1
            ks.append(k.reshape(view).to(self.device))
            modes.append((m.abs() / mmax).reshape(view))
        self.wavenumbers = tuple(ks)
        self._mode_fraction = tuple(modes)
        # the periodic axes' transform arguments, built once (the transforms run once per stage of every step)
        self._fft_dims = [a - ndim for a in self.periodic_axes]
        self._fft_sizes = [res[a] for a in self.periodic_axes]
        self._fft_1d = len(self.periodic_axes) == 1
        self._fft_2d = ndim == 2 and len(self.periodic_axes) == 2

    # ------------------------------------------------------------------ geometry
    @property
    def shape(self) -> tuple[int, ...]:
        """The physical shape of one channel (``resolution``)."""
        return self.resolution

    @property
    def spacing(self) -> tuple[float, ...]:
        """Grid spacing per axis (``L / N``)."""
        return tuple(length / n for length, n in zip(self.domain, self.resolution))

    def coordinates(self, dtype: torch.dtype | None = None) -> tuple[torch.Tensor, ...]:
        """Sample coordinates, one tensor per axis broadcastable to ``shape`` (see the module's grid convention).

        Args:
            dtype: Dtype of the coordinates (default: the grid's dtype).

        Returns:
            ``ndim`` tensors.
        """
        out = []
        for a in range(self.ndim):
            n, length = self.resolution[a], self.domain[a]
            j = torch.arange(n, dtype=torch.float64)
            x = j * length / n if self.boundaries[a] == "periodic" else (j + 0.5) * length / n
            view = [1] * self.ndim
            view[a] = -1
            out.append(x.reshape(view).to(device=self.device, dtype=dtype or self.dtype))
        return tuple(out)

    # ------------------------------------------------------------------ operators
    def wavenumber_squared(self) -> torch.Tensor:
        """``|k|^2`` on the spectral grid (float64).

        Returns:
            Tensor of shape ``spectral_shape``.
        """
        out = torch.zeros(self.spectral_shape, dtype=torch.float64, device=self.device)
        for k in self.wavenumbers:
            out = out + k * k
        return out

    def laplacian(self) -> torch.Tensor:
        """Symbol of the Laplacian, ``-|k|^2`` (float64, shape ``spectral_shape``); diagonal in every basis."""
        return -self.wavenumber_squared()

    def derivative(self, axis: int, dtype: torch.dtype | None = None) -> torch.Tensor:
        """Symbol ``i k`` of ``d/dx_axis`` on a periodic axis (Nyquist wavenumber set to zero).

        Args:
            axis: Spatial axis (0-based).
            dtype: Complex dtype of the result (default complex128).

        Returns:
            Complex tensor broadcastable to ``spectral_shape``.

        Raises:
            BoundaryError: If the axis has walls: a first derivative maps sines to cosines, so it is not diagonal
                in the sine/cosine basis.
        """
        if not 0 <= axis < self.ndim:
            raise ParameterError(f"axis {axis} out of range for a {self.ndim}-D grid")
        if self.boundaries[axis] != "periodic":
            raise BoundaryError(f"a first derivative along axis {axis} ({self.boundaries[axis]} walls) is not "
                                "diagonal in the sine/cosine basis; use periodic boundaries for this term")
        k = self.wavenumbers[axis].clone()
        n = self.resolution[axis]
        if n % 2 == 0:
            k = torch.where(self._mode_fraction[axis].to(k.device) == 1.0, torch.zeros_like(k), k)
        return (1j * k).to(dtype or torch.complex128)

    def dealias_cut(self, fraction: float = 2.0 / 3.0) -> int:
        """Number of entries of the last spectral axis that :meth:`dealias_mask` keeps (all axes periodic).

        A spectrum truncated to ``[..., :dealias_cut(fraction)]`` holds every mode the mask keeps; such a truncated
        spectrum is a valid input of :meth:`to_physical` on a periodic grid.

        Args:
            fraction: Kept fraction of the largest mode number (as for :meth:`dealias_mask`).

        Returns:
            The count.
        """
        if not (isinstance(fraction, (int, float)) and 0 < fraction <= 1):
            raise ParameterError(f"dealias fraction must be in (0, 1], got {fraction!r}")
        return int((self._mode_fraction[-1].reshape(-1) <= fraction + 1e-12).sum())

    def dealias_mask(self, fraction: float = 2.0 / 3.0) -> torch.Tensor:
        """Boolean mask of the modes kept by the dealiasing rule (``|m| <= fraction * m_max`` on every axis).

        Args:
            fraction: Kept fraction of the largest mode number per axis (2/3 rule by default; 1 keeps all).

        Returns:
            Bool tensor of shape ``spectral_shape``.
        """
        if not (isinstance(fraction, (int, float)) and 0 < fraction <= 1):
            raise ParameterError(f"dealias fraction must be in (0, 1], got {fraction!r}")
        mask = torch.ones(self.spectral_shape, dtype=torch.bool)
        for frac in self._mode_fraction:
            mask = mask & (frac <= fraction + 1e-12)
        return mask.to(self.device)

    # ------------------------------------------------------------------ transforms
    def to_spectral(self, u: torch.Tensor) -> torch.Tensor:
        """Forward transform over the last ``ndim`` axes of ``u`` (any leading batch/channel axes).

        Args:
            u: Real tensor ``(..., *resolution)``.

        Returns:
            Coefficients ``(..., *spectral_shape)``: complex when some axis is periodic, else real.
        """
        d = self.ndim
        for a in self.wall_axes:
            dim = a - d
            x = u.movedim(dim, -1)
            if self.boundaries[a] == "dirichlet":
                x = dst2(x, self._twiddles[a], self._signs[a])
            else:
                x = dct2(x, self._twiddles[a])
            u = x.movedim(-1, dim)
        if self._fft_1d:
            return torch.fft.rfft(u, dim=self._fft_dims[0])
        if self._fft_dims:
            return torch.fft.rfftn(u, dim=self._fft_dims)
        return u

    def to_physical(self, u_hat: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`to_spectral`.

        On a grid with periodic axes only, the last (half-spectrum) axis of ``u_hat`` may be shorter than in
        ``spectral_shape``: the missing highest modes are taken as zero (e.g. a spectrum truncated to
        :meth:`dealias_cut` entries, which saves part of the 2-D transform).

        Args:
            u_hat: Coefficients ``(..., *spectral_shape)``.

        Returns:
            Real tensor ``(..., *resolution)``.
        """
        if self._fft_2d and u_hat.shape[-1] < self.spectral_shape[-1]:
            return self._irfft2(u_hat)
        if self._fft_1d:
            u_hat = torch.fft.irfft(u_hat, n=self._fft_sizes[0], dim=self._fft_dims[0])
        elif self._fft_dims:
            u_hat = torch.fft.irfftn(u_hat, s=self._fft_sizes, dim=self._fft_dims)
        d = self.ndim
        for a in self.wall_axes:
            dim = a - d
            x = u_hat.movedim(dim, -1)
            if self.boundaries[a] == "dirichlet":
                x = idst2(x, self._twiddles[a], self._signs[a])
            else:
                x = idct2(x, self._twiddles[a])
            u_hat = x.movedim(-1, dim)
        return u_hat

    def _irfft2(self, u_hat: torch.Tensor) -> torch.Tensor:
        """Inverse 2-D real FFT of a spectrum truncated along its last axis (see :meth:`to_physical`).

        A complex inverse FFT along the first axis of the kept columns only, then a real one along the last axis.
        Between the two, the intermediate is put into row order by one 2-D transposed copy of all batch entries
        together (``.t().contiguous()`` of a column-ordered matrix, which torch copies in cache blocks), instead of
        the per-element strided copy that ``irfftn`` makes on the CPU. The reshapes are views when the complex FFT
        returns its output in column order (as the CPU backend does) and copies otherwise, so the result is the
        same either way.
        """
        n0, n1 = self.resolution
        y = torch.fft.ifft(u_hat, dim=-2)
        lead, cols = y.shape[:-2], y.shape[-1]
        t = y.transpose(-1, -2).reshape(-1, n0).t().contiguous()  # (n0, batch * cols), row order
        t = t.reshape((n0,) + tuple(lead) + (cols,)).movedim(0, -2)
        return torch.fft.irfft(t, n=n1, dim=-1)  # the zero padding to n1 // 2 + 1 entries restores the row order

    def __repr__(self) -> str:
        return (f"SpectralGrid(domain={self.domain}, resolution={self.resolution}, boundaries={self.boundaries}, "
                f"dtype={self.dtype}, device={self.device})")
