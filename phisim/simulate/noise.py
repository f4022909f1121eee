"""Random and analytic initial states: spectral noise, soft-edged rectangles, Gaussian vortices, uniform flows.

Randomness is explicit: every random function takes ``seed`` (an int: a fresh CPU ``torch.Generator`` seeded
with it, so the numbers are the same on every device) or ``generator`` (a ``torch.Generator`` that is
advanced, for a stream of batches); with neither, torch's global generator is used. Samples in a batch are
independent draws.

The recipes follow the reference experiments (EXPERIMENTS.md): E3's spectral noise, E4's hot rectangles
and E5's Gaussian vortex and uniform velocity.
"""

from __future__ import annotations

import torch

from phisim.boundary import Boundary
from phisim.checks import check_bool, check_int, check_number, check_seed
from phisim.errors import ParameterError, ShapeError
from phisim.field import CenteredGrid, StaggeredGrid
from phisim.grid import Grid

__all__ = ["spectral_noise", "rectangles", "random_rectangles", "gaussian_vortex", "uniform_velocity"]


# ---- helpers ---------------------------------------------------------------------------------------------


def _rng(seed: int | None, generator: torch.Generator | None) -> torch.Generator | None:
    if seed is not None and generator is not None:
        raise ParameterError("give either seed or generator, not both")
    if generator is not None:
        if not isinstance(generator, torch.Generator):
            raise ParameterError(f"generator must be a torch.Generator, got {type(generator).__name__}")
        return generator
    seed = check_seed(seed)
    if seed is None:
        return None
    g = torch.Generator()
    g.manual_seed(seed)
    return g


def _gen_device(gen: torch.Generator | None):
    return gen.device if gen is not None else torch.device("cpu")


def _check_batch(batch_size) -> int:
    return check_int(batch_size, "batch_size", minimum=1)


def _check_range(value, name: str, *, integer: bool = False, minimum=None) -> tuple:
    """A ``(lo, hi)`` pair of numbers (ints with ``integer``) with ``lo <= hi``."""
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 2:
        raise ParameterError(f"{name} must be a pair (lo, hi), got {value!r}")
    if integer:
        lo, hi = (check_int(v, f"{name}[{i}]", minimum=minimum) for i, v in enumerate(value))
    else:
        lo, hi = (check_number(v, f"{name}[{i}]", minimum=minimum) for i, v in enumerate(value))
    if hi < lo:
        raise ParameterError(f"{name} must be a range (lo, hi) with hi >= lo, got {tuple(value)}")
    return lo, hi


def _as_real_tensor(x, name: str, dtype=None, device=None) -> torch.Tensor:
    if isinstance(x, (str, bytes)) or x is None:
        raise ParameterError(f"{name} must be a number, a sequence of numbers or a tensor, got {x!r}")
    try:
        t = torch.as_tensor(x, dtype=dtype, device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ParameterError(f"{name} must be a number, a sequence of numbers or a tensor, got {x!r}") from exc
    if t.is_complex() or t.dtype == torch.bool:
        raise ParameterError(f"{name} must be real, got dtype {t.dtype}")
    return t


def _check_grid(grid) -> Grid:
    if not isinstance(grid, Grid):
        raise ParameterError(f"grid must be a phisim Grid, got {type(grid).__name__}")
    return grid


# ---- spectral noise --------------------------------------------------------------------------------------


def spectral_noise(grid: Grid, batch_size: int = 1, *, power: float = 2.0, scale: float = 10.0,
                   cutoff: float = 0.1, channels: int | None = None, normalize: bool = True,
                   boundary="periodic", seed: int | None = None, generator: torch.Generator | None = None,
                   dtype: torch.dtype | None = None, device=None) -> CenteredGrid:
    """Smooth random field with a power-law spectrum (the E3 recipe, PhiFlow's ``Noise``).

    For every Fourier mode with integer wavenumbers ``m`` (numpy ``fftfreq(n) * n`` per axis) the physical
    wavenumber is ``k_a = m_a * scale / size_a``. The spectrum is complex white noise times
    ``|k|^(-power)``, with every mode of ``|k|^2 <= cutoff`` (the mean included) set to zero. The field is
    the real part of the inverse FFT; with ``normalize`` each sample (and channel) is shifted and scaled to
    zero mean and unit standard deviation. The power spectrum thus falls like ``|k|^(-2 power)``.

    Args:
        grid: The grid (1-D, 2-D or 3-D); ``size`` enters ``k``.
        batch_size: Number of independent samples ``B``.
        power: Exponent of the amplitude falloff (E3: 2, i.e. amplitude ``1/|k|^2``).
        scale: Wavenumber scale (E3: 10); larger values give finer structures.
        cutoff: Modes with ``|k|^2 <= cutoff`` are removed (E3: 0.1).
        channels: ``None`` for a scalar field ``(B, *res)``; an int for ``(B, channels, *res)`` with
            independent channels (e.g. ``grid.rank`` for a random velocity).
        normalize: Normalise each sample to zero mean and unit standard deviation.
        boundary: Boundary of the returned field (the noise itself is periodic).
        seed: Seed of a fresh generator (reproducible on every device).
        generator: A ``torch.Generator`` to draw from instead.
        dtype: Floating dtype of the result (default: torch's default). The noise is drawn in float64.
        device: Device of the result.

    Returns:
        A ``CenteredGrid``.

    Raises:
        ParameterError: For a non-positive ``batch_size``/``scale``, a negative ``cutoff``, both ``seed`` and
            ``generator``, or a grid whose every mode is cut off.
    """
    grid = _check_grid(grid)
    batch_size = _check_batch(batch_size)
    scale = check_number(scale, "scale", minimum=0, min_open=True)
    cutoff = check_number(cutoff, "cutoff", minimum=0)
    power = check_number(power, "power")
    channels = check_int(channels, "channels", minimum=1, allow_none=True)
    normalize = check_bool(normalize, "normalize")
    gen = _rng(seed, generator)
    gdev = _gen_device(gen)
    k2 = torch.zeros(grid.resolution, dtype=torch.float64, device=gdev)
    for a, (n, size) in enumerate(zip(grid.resolution, grid.size)):
        view = [1] * grid.rank
        view[a] = n
        k = torch.fft.fftfreq(n, d=1.0 / n, dtype=torch.float64, device=gdev) * (scale / size)
        k2 = k2 + k.reshape(view) ** 2
    keep = k2 > cutoff
    if not bool(keep.any()):
        raise ParameterError(
            f"every Fourier mode of {grid} has |k|^2 <= cutoff={cutoff} (scale={scale}); raise scale or lower cutoff"
        )
    amplitude = torch.where(keep, k2.clamp_min(1e-300) ** (-0.5 * power), torch.zeros_like(k2))
    lead = (batch_size,) if channels is None else (batch_size, channels)
    shape = lead + grid.resolution
    re = torch.randn(shape, generator=gen, dtype=torch.float64, device=gdev)
    im = torch.randn(shape, generator=gen, dtype=torch.float64, device=gdev)
    spectrum = torch.complex(re, im) * amplitude
    axes = tuple(range(len(lead), len(shape)))
    values = torch.fft.ifftn(spectrum, dim=axes).real
    if normalize:
        values = values - values.mean(dim=axes, keepdim=True)
        std = values.std(dim=axes, keepdim=True, unbiased=False)
        values = values / torch.where(std > 0, std, torch.ones_like(std))
    values = values.to(dtype=dtype or torch.get_default_dtype(), device=device if device is not None else gdev)
    return CenteredGrid(values, grid, boundary)


# ---- rectangles ------------------------------------------------------------------------------------------


def _as_batched(x, batch: int | None, width: int, name: str, dtype, device) -> torch.Tensor:
    """Bring boxes/centres to ``(B, K, width)`` (``width=0`` for per-box scalars ``(B, K)``)."""
    t = _as_real_tensor(x, name, dtype, device)
    if width:
        if t.ndim == 0 or t.shape[-1] != width:
            raise ShapeError(f"{name} must end in an axis of size {width}, got shape {tuple(t.shape)}")
        t = t.reshape((1, 1, width)) if t.ndim == 1 else t
        t = t[:, None, :] if t.ndim == 2 else t
        if t.ndim != 3:
            raise ShapeError(
                f"{name} must have shape ({width},), (B, {width}) or (B, K, {width}), got {tuple(t.shape)}")
    else:
        t = t.reshape(1, 1) if t.ndim == 0 else t
        t = t[:, None] if t.ndim == 1 else t
        if t.ndim != 2:
            raise ShapeError(f"{name} must be a number, (B,) or (B, K), got shape {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise ParameterError(f"{name} contains NaN/Inf")
    return t


def _coverage(grid: Grid, lower: torch.Tensor, upper: torch.Tensor, strength: torch.Tensor) -> torch.Tensor:
    """Sum over boxes of ``strength * (covered fraction of each cell)``: ``(B, *res)``."""
    factors = []
    for a in range(grid.rank):
        faces = grid.face_coords(a, lower.dtype, lower.device)
        lo_f, hi_f = faces[:-1], faces[1:]  # (n,)
        lo_b, hi_b = lower[..., a:a + 1], upper[..., a:a + 1]  # (B, K, 1)
        overlap = (torch.minimum(hi_b, hi_f) - torch.maximum(lo_b, lo_f)).clamp_min(0) / grid.dx[a]
        factors.append(overlap)  # (B, K, n_a)
    letters = "ijk"[: grid.rank]
    spec = "bq," + ",".join(f"bq{c}" for c in letters) + "->b" + letters
    return torch.einsum(spec, strength, *factors)


def rectangles(grid: Grid, lower, upper, strength=1.0, *, boundary="periodic", dtype: torch.dtype | None = None,
               device=None) -> CenteredGrid:
    """Sum of axis-aligned boxes, each cell weighted by the exact fraction of its volume the box covers.

    Cell ``c`` gets ``sum_k strength_k * prod_a |[lo_ka, hi_ka] ∩ cell_a| / dx_a``, so the field integrates
    to ``sum_k strength_k * volume(box_k ∩ domain)`` exactly. Boxes do not wrap around periodic sides.

    Args:
        grid: The grid.
        lower: Lower corners in physical units: ``(d,)``, ``(B, d)`` or ``(B, K, d)`` (K boxes per sample).
        upper: Upper corners, same layout as ``lower``.
        strength: Per box value: a number, ``(B,)`` or ``(B, K)``.
        boundary: Boundary of the returned field.
        dtype: Floating dtype (default: torch's default).
        device: Device.

    Returns:
        A scalar ``CenteredGrid`` ``(B, *res)``.

    Raises:
        ShapeError: For corner/strength arrays that do not fit each other or the grid.
        ParameterError: For NaN/Inf corners or an upper corner below a lower one.
    """
    grid = _check_grid(grid)
    dtype = dtype or torch.get_default_dtype()
    lo = _as_batched(lower, None, grid.rank, "lower", dtype, device)
    hi = _as_batched(upper, None, grid.rank, "upper", dtype, device)
    s = _as_batched(strength, None, 0, "strength", dtype, device)
    try:
        B = max(lo.shape[0], hi.shape[0], s.shape[0])
        K = max(lo.shape[1], hi.shape[1], s.shape[1])
        lo = lo.expand(B, K, grid.rank)
        hi = hi.expand(B, K, grid.rank)
        s = s.expand(B, K)
    except RuntimeError as exc:
        raise ShapeError(f"lower {tuple(lo.shape)}, upper {tuple(hi.shape)} and strength {tuple(s.shape)} "
                         "do not broadcast") from exc
    if bool((hi < lo).any()):
        raise ParameterError("every upper corner must be >= its lower corner")
    return CenteredGrid(_coverage(grid, lo, hi, s), grid, boundary)


def random_rectangles(grid: Grid, batch_size: int = 1, *, count: tuple[int, int] = (4, 10),
                      max_half_size: float = 10.0, strength: tuple[float, float] = (0.0, 1.0),
                      margin: float = 0.1, boundary="periodic", seed: int | None = None,
                      generator: torch.Generator | None = None, dtype: torch.dtype | None = None,
                      device=None) -> CenteredGrid:
    """Random hot rectangles with soft (exactly area-weighted) edges, the E4 initial state.

    Per sample: ``count[0]..count[1]`` boxes (uniform integer); centres uniform in the middle
    ``1 - 2 margin`` of the domain; half-sizes per axis uniform in ``[0, max_half_size)`` cells; strengths
    uniform in ``[strength[0], strength[1])``. Each centre is then clamped so its box lies inside the domain
    (as the E4 reference does). Overlapping boxes add up. See :func:`rectangles` for the coverage rule.

    Args:
        grid: The grid.
        batch_size: Number of samples ``B``.
        count: Inclusive range of the number of boxes per sample (E4: 4 to 10).
        max_half_size: Upper limit of the half-size, in cells (times ``dx`` per axis; E4: 10).
        strength: Range of the box values (E4: ``[0, 1)``).
        margin: Fraction of the domain kept free of centres at each side (E4: 0.1, the middle 80%).
        boundary: Boundary of the returned field.
        seed: Seed of a fresh generator.
        generator: A ``torch.Generator`` to draw from instead.
        dtype: Floating dtype (default: torch's default).
        device: Device of the result.

    Returns:
        A scalar ``CenteredGrid`` ``(B, *res)``.

    Raises:
        ParameterError: For invalid ranges or both ``seed`` and ``generator``.
    """
    grid = _check_grid(grid)
    batch_size = _check_batch(batch_size)
    c0, c1 = _check_range(count, "count", integer=True, minimum=0)
    if c1 < 1:
        raise ParameterError(f"count must be an inclusive range 0 <= lo <= hi, hi >= 1, got {count}")
    max_half_size = check_number(max_half_size, "max_half_size", minimum=0)
    margin = check_number(margin, "margin", minimum=0, maximum=0.5, max_open=True)
    s0, s1 = _check_range(strength, "strength")
    gen = _rng(seed, generator)
    gdev = _gen_device(gen)
    B, K, d = batch_size, c1, grid.rank
    f64 = torch.float64
    n_boxes = torch.randint(c0, c1 + 1, (B, 1), generator=gen, device=gdev)
    centre_u = torch.rand((B, K, d), generator=gen, dtype=f64, device=gdev)
    half_u = torch.rand((B, K, d), generator=gen, dtype=f64, device=gdev)
    strength_u = torch.rand((B, K), generator=gen, dtype=f64, device=gdev)
    lower = torch.tensor(grid.lower, dtype=f64, device=gdev)
    size = torch.tensor(grid.size, dtype=f64, device=gdev)
    dx = torch.tensor(grid.dx, dtype=f64, device=gdev)
    centre = lower + size * (margin + (1 - 2 * margin) * centre_u)
    half = torch.minimum(half_u * max_half_size * dx, 0.5 * size)
    centre = torch.maximum(torch.minimum(centre, lower + size - half), lower + half)
    active = torch.arange(K, device=gdev)[None, :] < n_boxes
    s = (s0 + (s1 - s0) * strength_u) * active
    values = _coverage(grid, centre - half, centre + half, s)
    values = values.to(dtype=dtype or torch.get_default_dtype(), device=device if device is not None else gdev)
    return CenteredGrid(values, grid, boundary)


# ---- velocities ------------------------------------------------------------------------------------------


def _vortex_velocity(points: torch.Tensor, centre: torch.Tensor, strength: torch.Tensor, sigma: float,
                     axis: int, period: torch.Tensor | None) -> torch.Tensor:
    """Velocity ``(B, *P, d)`` of Gaussian vortices at ``points`` ``(*P, d)``."""
    d = points.shape[-1]
    B, K = strength.shape
    p = points.reshape(1, 1, -1, d)
    diff = p - centre[:, :, None, :]  # (B, K, N, d)
    if period is not None:
        safe = torch.where(period > 0, period, torch.ones_like(period))
        diff = diff - torch.where(period > 0, period * torch.round(diff / safe), torch.zeros_like(diff))
    weight = strength[:, :, None] * torch.exp(-0.5 * (diff ** 2).sum(-1) / sigma ** 2)  # (B, K, N)
    if d == 2:
        rot = torch.stack([-diff[..., 1], diff[..., 0]], dim=-1)
    else:  # e_axis x diff
        e = torch.zeros(3, dtype=diff.dtype, device=diff.device)
        e[axis] = 1.0
        rot = torch.cross(e.expand_as(diff), diff, dim=-1)
    v = (weight[..., None] * rot).sum(1)  # (B, N, d)
    return v.reshape(B, *points.shape[:-1], d)


def gaussian_vortex(grid: Grid, centre, strength, sigma: float, *, staggered: bool = True, boundary="periodic",
                    axis: int = 2, wrap: bool = False, batch_size: int | None = None,
                    dtype: torch.dtype | None = None, device=None) -> StaggeredGrid | CenteredGrid:
    """Velocity of one or more Gaussian vortices (E5; PhiFlow's ``AngularVelocity`` with a Gaussian falloff).

    ``v(x) = sum_k s_k exp(-|x - c_k|^2 / (2 sigma^2)) (e_axis x (x - c_k))``; in 2-D ``e_axis x d`` is
    ``(-d_y, d_x)`` (counter-clockwise for ``s > 0``). Each term is divergence-free analytically (the falloff
    depends on ``|d|`` only, and ``d . (e x d) = 0``). Staggered output samples component ``i`` at the
    faces normal to axis ``i`` (so its discrete divergence is ``O(dx^2)``); centred output samples every
    component at the cell centres.

    Args:
        grid: A 2-D or 3-D grid.
        centre: Vortex centres in physical units: ``(d,)``, ``(B, d)`` or ``(B, K, d)``.
        strength: Angular strength: a number, ``(B,)`` or ``(B, K)`` (E5: uniform in ``[-2, 2]``).
        sigma: Falloff length in physical units (E5: 20).
        staggered: Return a ``StaggeredGrid`` (default) or a centred vector ``CenteredGrid``.
        boundary: Velocity boundary of the result.
        axis: Rotation axis in 3-D (0, 1 or 2); ignored in 2-D.
        wrap: Measure ``x - c`` by the nearest periodic image on periodic axes (E5's reference does not).
        batch_size: Batch size when ``centre`` and ``strength`` carry none (default 1).
        dtype: Floating dtype (default: torch's default).
        device: Device.

    Returns:
        ``StaggeredGrid`` or ``CenteredGrid`` ``(B, d, *res)``.

    Raises:
        ParameterError: For a 1-D grid, ``sigma <= 0``, a bad ``axis`` or NaN inputs.
        ShapeError: For centres/strengths that do not fit the grid or each other.
    """
    grid = _check_grid(grid)
    if grid.rank not in (2, 3):
        raise ParameterError(f"vortices need a 2-D or 3-D grid, got {grid}")
    sigma = check_number(sigma, "sigma", minimum=0, min_open=True)
    axis = check_int(axis, "axis", minimum=0, maximum=2)
    staggered, wrap = check_bool(staggered, "staggered"), check_bool(wrap, "wrap")
    dtype = dtype or torch.get_default_dtype()
    c = _as_batched(centre, None, grid.rank, "centre", dtype, device)
    s = _as_batched(strength, None, 0, "strength", dtype, device)
    B = max(c.shape[0], s.shape[0], 1 if batch_size is None else _check_batch(batch_size))
    K = max(c.shape[1], s.shape[1])
    try:
        c = c.expand(B, K, grid.rank)
        s = s.expand(B, K)
    except RuntimeError as exc:
        raise ShapeError(f"centre {tuple(c.shape)} and strength {tuple(s.shape)} do not fit batch {B}") from exc
    period = None
    if wrap:
        periodic = Boundary.create(boundary, grid.rank).periodic_axes
        period = torch.tensor([sz if p else 0.0 for sz, p in zip(grid.size, periodic)], dtype=dtype,
                              device=c.device)
    if not staggered:
        v = _vortex_velocity(grid.cell_centers(dtype, c.device), c, s, sigma, axis, period)
        return CenteredGrid(torch.movedim(v, -1, 1), grid, boundary)
    comps = []
    for i in range(grid.rank):
        v = _vortex_velocity(grid.face_centers(i, dtype, c.device), c, s, sigma, axis, period)
        comps.append(v[..., i])
    return StaggeredGrid(tuple(comps), grid, boundary)


def uniform_velocity(grid: Grid, velocity, *, staggered: bool = True, boundary="periodic",
                     batch_size: int | None = None, dtype: torch.dtype | None = None,
                     device=None) -> StaggeredGrid | CenteredGrid:
    """A spatially constant velocity, possibly different per sample (E5's drift).

    Args:
        grid: The grid.
        velocity: ``(d,)`` shared by all samples or ``(B, d)`` per sample (a tensor keeps its graph).
        staggered: Return a ``StaggeredGrid`` (default) or a centred vector ``CenteredGrid``.
        boundary: Velocity boundary of the result. With walls the normal velocity on boundary faces is
            still the uniform value (call ``with_boundary_faces()`` to impose the walls).
        batch_size: Batch size when ``velocity`` carries none (default 1).
        dtype: Floating dtype (default: the tensor's, else torch's default).
        device: Device.

    Returns:
        ``StaggeredGrid`` or ``CenteredGrid`` ``(B, d, *res)``.

    Raises:
        ShapeError: If ``velocity`` does not have one component per axis.
    """
    grid = _check_grid(grid)
    staggered = check_bool(staggered, "staggered")
    v = _as_real_tensor(velocity, "velocity", device=device)
    v = v.to(dtype or (v.dtype if v.is_floating_point() else torch.get_default_dtype()))
    if v.ndim == 1:
        v = v[None]
    if v.ndim != 2 or v.shape[-1] != grid.rank:
        raise ShapeError(f"velocity must have shape ({grid.rank},) or (B, {grid.rank}), got {tuple(v.shape)}")
    if v.device.type == "cpu" and not bool(torch.isfinite(v.detach()).all()):
        raise ParameterError("velocity contains NaN/Inf")
    B = v.shape[0]
    if batch_size is not None:
        batch_size = _check_batch(batch_size)
        if B not in (1, batch_size):
            raise ShapeError(f"velocity has batch {B}, batch_size is {batch_size}")
        B = batch_size
        v = v.expand(B, grid.rank)
    view = (B,) + (1,) * grid.rank
    if not staggered:
        vals = v.reshape(B, grid.rank, *(1,) * grid.rank).expand(B, grid.rank, *grid.resolution)
        return CenteredGrid(vals.clone(), grid, boundary)
    comps = tuple(v[:, i].reshape(view).expand(B, *grid.face_shape(i)).clone() for i in range(grid.rank))
    return StaggeredGrid(comps, grid, boundary)
