"""FFT engines: agreement with scipy.fft / numpy.fft, adjoint-based gradients, engine selection."""

import numpy as np
import pytest
import scipy.fft as sfft
import torch

from phisim.errors import ParameterError, ShapeError
from phisim.spectral import fft

ENGINES = fft.available_engines()


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize(
    "shape,axes", [((7,), None), ((8,), None), ((3, 5, 6), (1, 2)), ((2, 3, 4, 5), (1, 2, 3))]
)
@pytest.mark.parametrize("norm", ["backward", "ortho", "forward"])
def test_dct_dst_match_scipy(engine, shape, axes, norm):
    rng = np.random.default_rng(0)
    x = rng.standard_normal(shape)
    t = torch.from_numpy(x)
    for ours, ref in (
        (fft.dctn, sfft.dctn),
        (fft.idctn, sfft.idctn),
        (fft.dstn, sfft.dstn),
        (fft.idstn, sfft.idstn),
    ):
        for typ in (2, 3):
            got = ours(t, typ, axes, norm, engine=engine).numpy()
            want = ref(x, type=typ, axes=axes, norm=norm)
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())


@pytest.mark.parametrize("engine", ENGINES)
def test_type4_and_mixed_kinds_match_scipy(engine):
    x = np.random.default_rng(1).standard_normal((2, 5, 6, 7))
    got = fft.r2rn(torch.from_numpy(x), ("dct4", "dst2", "dst4"), (1, 2, 3), engine=engine).numpy()
    want = sfft.dst(sfft.dst(sfft.dct(x, 4, axis=1), 2, axis=2), 4, axis=3)
    np.testing.assert_allclose(got, want, atol=1e-12 * np.abs(want).max())


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("shape", [(6,), (5, 7), (4, 5, 6)])
def test_rfftn_roundtrip_matches_numpy(engine, shape):
    x = np.random.default_rng(2).standard_normal((2,) + shape)
    axes = tuple(range(1, len(shape) + 1))
    X = fft.rfftn(torch.from_numpy(x), axes, engine=engine)
    np.testing.assert_allclose(X.numpy(), np.fft.rfftn(x, axes=axes), atol=1e-12 * x.size)
    back = fft.irfftn(X, shape, axes, engine=engine)
    np.testing.assert_allclose(back.numpy(), x, atol=1e-13)


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("kinds", [("dct2", "dst3"), ("dst2", "dct3"), ("dct4", "dst4")])
def test_r2r_gradcheck_and_gradgradcheck(engine, kinds):
    x = torch.randn(2, 5, 6, dtype=torch.float64, requires_grad=True)
    f = lambda x: fft.r2rn(x, kinds, (1, 2), engine=engine)  # noqa: E731
    assert torch.autograd.gradcheck(f, (x,))
    assert torch.autograd.gradgradcheck(f, (x,))


@pytest.mark.parametrize("kinds", [("dst1", "dct2"), ("dct1", "dst3"), ("dct4", "dst4"), ("dst2", "dct3")])
def test_r2r_float32_values_and_gradients_match_float64(kinds):
    # float32 real-to-real transforms (pocketfft with the pyfftw engine) against float64 and scipy, both ways
    x = torch.randn(2, 6, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(11))
    g = torch.randn(2, 6, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(12))
    want = x.numpy()
    for kind, ax in zip(kinds, (1, 2)):
        want = (sfft.dct if kind.startswith("dct") else sfft.dst)(want, type=int(kind[3]), axis=ax)
    grads = {}
    for dtype in (torch.float32, torch.float64):
        xs = x.to(dtype).requires_grad_(True)
        y = fft.r2rn(xs, kinds, (1, 2))
        np.testing.assert_allclose(y.detach().double().numpy(), want, rtol=0,
                                   atol=(3e-6 if dtype == torch.float32 else 1e-12) * np.abs(want).max())
        (y * g.to(dtype)).sum().backward()
        grads[dtype] = xs.grad.double()
    torch.testing.assert_close(grads[torch.float32], grads[torch.float64], rtol=0,
                               atol=3e-6 * float(grads[torch.float64].abs().max()))


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("shape", [(5, 6), (5, 7)])
def test_rfft_gradients(engine, shape):
    x = torch.randn(2, *shape, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: fft.rfftn(x, (1, 2), engine=engine), (x,))
    X = torch.randn(2, shape[0], shape[1] // 2 + 1, dtype=torch.complex128, requires_grad=True)
    assert torch.autograd.gradcheck(lambda X: fft.irfftn(X, shape, (1, 2), engine=engine), (X,))
    assert torch.autograd.gradgradcheck(lambda X: fft.irfftn(X, shape, (1, 2), engine=engine), (X,))


@pytest.mark.skipif("pyfftw" not in ENGINES, reason="pyfftw not installed")
def test_torch_engine_equals_pyfftw_engine_float32():
    x = torch.randn(3, 16, 12)
    for fn in (fft.dctn, fft.dstn, fft.idctn, fft.idstn):
        a = fn(x, 2, (1, 2), "ortho", engine="torch")
        b = fn(x, 2, (1, 2), "ortho", engine="pyfftw")
        assert a.dtype == b.dtype == torch.float32
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


def test_engine_selection_and_errors():
    x = torch.zeros(4, 4)
    assert fft.resolve_engine(x, "torch") == "torch"
    assert fft.resolve_engine(x, "auto") in ENGINES
    with pytest.raises(ParameterError):
        fft.resolve_engine(x, "cufft")
    with pytest.raises(ParameterError):
        fft.dctn(x, type=1)
    with pytest.raises(ParameterError):
        fft.dctn(x, norm="unitary")
    with pytest.raises(ParameterError):
        fft.dctn(torch.zeros(4, dtype=torch.int64))
    with pytest.raises(ShapeError):
        fft.dctn(x, axes=(0, 0))
    with pytest.raises(ParameterError):
        fft.FFTSettings(threads=0)
    with pytest.raises(ParameterError):
        fft.r2rn(x, ("dct2",), (0, 1))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.cuda
def test_cuda_dct_dst_match_scipy():
    x = np.random.default_rng(3).standard_normal((2, 9, 8))
    t = torch.from_numpy(x).cuda()
    for ours, ref in (
        (fft.dctn, sfft.dctn),
        (fft.dstn, sfft.dstn),
        (fft.idctn, sfft.idctn),
        (fft.idstn, sfft.idstn),
    ):
        got = ours(t, 2, (1, 2), "ortho").cpu().numpy()
        np.testing.assert_allclose(got, ref(x, 2, axes=(1, 2), norm="ortho"), atol=1e-12)
    tt = t.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda x: fft.r2rn(x, ("dst2", "dct4"), (1, 2)), (tt,))


def test_fourier_multiply_matches_reference_and_is_self_adjoint():
    from phisim.spectral.fft import available_engines, fourier_multiply

    gen = torch.Generator().manual_seed(4)
    x = torch.randn(3, 8, 6, dtype=torch.float64, generator=gen)
    k2 = torch.fft.fftfreq(8, dtype=torch.float64)[:, None] ** 2 + torch.fft.rfftfreq(6, dtype=torch.float64) ** 2
    mult = torch.exp(-3.0 * k2)
    expected = torch.fft.irfftn(torch.fft.rfftn(x, dim=(1, 2)) * mult, s=(8, 6), dim=(1, 2))
    for engine in available_engines():
        y = fourier_multiply(x, mult, (1, 2), engine=engine)
        torch.testing.assert_close(y, expected, rtol=1e-12, atol=1e-13)
        z = torch.randn(3, 8, 6, dtype=torch.float64, generator=gen)  # <z, A x> = <A z, x>
        torch.testing.assert_close((z * y).sum(), (fourier_multiply(z, mult, (1, 2), engine=engine) * x).sum())
        xs = x[:1].clone().requires_grad_(True)
        assert torch.autograd.gradcheck(lambda v, e=engine: fourier_multiply(v, mult, (1, 2), engine=e), (xs,))
    with pytest.raises(ParameterError):
        fourier_multiply(x, mult.to(torch.complex128), (1, 2))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("kinds,inverse", [(("dct2", "dct2"), ("dct3", "dct3")), (("dst2", "dct4"), ("dst3", "dct4"))])
def test_r2r_multiply_equals_composed_transforms(dtype, kinds, inverse):
    gen = torch.Generator().manual_seed(5)
    x = torch.randn(3, 8, 6, dtype=torch.float64, generator=gen).to(dtype)
    pre = (torch.rand(1, 8, 6, generator=gen) > 0.3).to(dtype)
    mult = torch.rand(8, 6, dtype=torch.float64, generator=gen).to(dtype)
    y = fft.r2r_multiply(x, kinds, inverse, (1, 2), mult, pre=pre, engine="pyfftw" if "pyfftw" in ENGINES else None)
    if "pyfftw" not in ENGINES:
        assert y is None
        return
    ref = fft.r2rn(fft.r2rn(x * pre, kinds, (1, 2), engine="torch") * mult, inverse, (1, 2), engine="torch")
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    torch.testing.assert_close(y, ref, rtol=tol, atol=tol * float(ref.abs().max()))
    assert y.dtype == dtype and y.shape == x.shape
    y2 = fft.r2r_multiply(x, kinds, inverse, (1, 2), mult, pre=pre, engine="pyfftw")
    assert y2.data_ptr() != y.data_ptr() and torch.equal(y, y2)  # each call returns its own tensor
    # the fast path declines what it cannot do, so callers fall back to the composed transforms
    assert fft.r2r_multiply(x, kinds, inverse, (1, 2), mult, engine="torch") is None
    # a multiplier or pre-factor with a gradient (e.g. a tensor viscosity) must not be detached silently
    assert fft.r2r_multiply(x, kinds, inverse, (1, 2), mult.clone().requires_grad_(True), engine="pyfftw") is None
    assert fft.r2r_multiply(x, kinds, inverse, (1, 2), mult, pre=pre.clone().requires_grad_(True),
                            engine="pyfftw") is None
    assert fft.r2r_multiply(x.requires_grad_(True), kinds, inverse, (1, 2), mult, engine="pyfftw") is None


def _scipy_r2r(x: np.ndarray, kind: str, axis: int) -> np.ndarray:
    fn = sfft.dct if kind.startswith("dct") else sfft.dst
    return fn(x, type=int(kind[3]), axis=axis)


@pytest.mark.skipif("pyfftw" not in ENGINES, reason="the fast path runs with the pyfftw engine")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("kinds,inverse", [(("dst1", "dst2"), ("dst1", "dst3")), (("dct1", "dct3"), ("dct1", "dct2")),
                                           (("dst3", "dct4"), ("dst2", "dst4")), (("dct2", "dst1"), ("dct3", "dst1"))])
@pytest.mark.parametrize("transposed", [False, True])
def test_r2r_multiply_one_axis_transforms_match_scipy(dtype, kinds, inverse, transposed):
    # every kind, in place into a strided view (the interior of a larger array), and the transposed layout
    # that large planes take (forced here by a zero size threshold)
    if transposed:
        fft.set_fft_settings(transpose_bytes=0)  # restored by the conftest's _default_fft_settings fixture
    gen = torch.Generator().manual_seed(7)
    x = torch.randn(2, 9, 7, dtype=torch.float64, generator=gen).to(dtype)
    mult = torch.rand(9, 7, dtype=torch.float64, generator=gen).to(dtype)
    pre = torch.rand(1, 9, 7, dtype=torch.float64, generator=gen).to(dtype)
    xs, ms, ps = (t.double().numpy() for t in (x, mult, pre))
    spec = xs * ps
    for kind, ax in zip(kinds, (1, 2)):
        spec = _scipy_r2r(spec, kind, ax)
    want = spec * ms
    for kind, ax in zip(inverse, (1, 2)):
        want = _scipy_r2r(want, kind, ax)
    big = torch.full((2, 11, 10), 5.0, dtype=dtype)
    view = big[:, 1:10, 2:9]
    y = fft.r2r_multiply(x, kinds, inverse, (1, 2), mult, pre=pre, engine="pyfftw", out=view)
    assert y is view and y.dtype == dtype
    tol = 1e-12 if dtype == torch.float64 else 3e-5
    np.testing.assert_allclose(y.double().numpy(), want, rtol=0, atol=tol * np.abs(want).max())
    outside = torch.ones_like(big, dtype=torch.bool)
    outside[:, 1:10, 2:9] = False
    assert bool((big[outside] == 5.0).all())  # nothing written outside the view
    fresh = fft.r2r_multiply(x, kinds, inverse, (1, 2), mult, pre=pre, engine="pyfftw")
    torch.testing.assert_close(fresh, y, rtol=0, atol=0)
    with pytest.raises(ShapeError, match="out"):
        fft.r2r_multiply(x, kinds, inverse, (1, 2), mult, engine="pyfftw", out=big)


def test_r2r_multiply_is_reproducible_in_a_fresh_process():
    import subprocess
    import sys

    code = ("import torch; from phisim import fft; g = torch.Generator().manual_seed(3); "
            "x = torch.randn(1, 40, 33, generator=g); m = torch.rand(40, 33, generator=g); "
            "y = fft.r2r_multiply(x, ('dst1', 'dst2'), ('dst1', 'dst3'), (1, 2), m); "
            "print(None if y is None else y.double().sum().item().hex())")
    outs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
            for _ in range(2)]
    assert outs[0] == outs[1] and outs[0].strip()


# ----------------------------------------------------------------------------------------------
# settings and bounded plan caches


def test_settings_defaults_and_validation():
    s = fft.FFTSettings()
    assert s.planner_effort == "FFTW_ESTIMATE" and s.deterministic and s.plan_cache_size == 32
    assert s.transpose_bytes == s.wall_transpose_bytes == 384 * 1024
    for bad in ({"plan_cache_size": 0}, {"plan_cache_size": 2.5}, {"transpose_bytes": -1},
                {"wall_transpose_bytes": None}, {"threads": True}, {"planner_effort": "FFTW_FAST"}):
        with pytest.raises(ParameterError):
            fft.FFTSettings(**bad)
    with fft.fft_settings(plan_cache_size=3) as inside:
        assert fft.get_fft_settings() is inside and inside.plan_cache_size == 3
    assert fft.get_fft_settings().plan_cache_size == 32


@pytest.mark.skipif("pyfftw" not in ENGINES, reason="plan caches belong to the pyfftw engine")
def test_plan_caches_are_bounded_lru():
    from phisim.spectral import fftw as fft_fftw

    fft_fftw.clear_plans()
    xs = [torch.randn(2, n, 6, dtype=torch.float64) for n in (3, 4, 5, 6, 7)]
    with fft.fft_settings(plan_cache_size=3):
        for x in xs:
            X = fft.rfftn(x, (1, 2), engine="pyfftw")
            np.testing.assert_allclose(X.numpy(), np.fft.rfftn(x.numpy(), axes=(1, 2)), atol=1e-12)
            fft.fourier_multiply(x, torch.ones(x.shape[1], 4, dtype=torch.float64), (1, 2), engine="pyfftw")
        assert len(fft_fftw.PLANS) == 3 and len(fft_fftw.MULTIPLIER_PLANS) == 3
        assert [k[1][1] for k in fft_fftw.PLANS.keys()] == [5, 6, 7]  # the least recently used went first
        fft.rfftn(xs[2], (1, 2), engine="pyfftw")  # a hit moves to the end
        fft.rfftn(xs[0], (1, 2), engine="pyfftw")  # a miss evicts the oldest (n=6)
        assert [k[1][1] for k in fft_fftw.PLANS.keys()] == [7, 5, 3]
    with fft.fft_settings(plan_cache_size=1):  # a smaller bound applies at the next use
        fft.rfftn(xs[0], (1, 2), engine="pyfftw")
        assert len(fft_fftw.PLANS) == 1
    fft_fftw.clear_plans()
    assert len(fft_fftw.PLANS) == len(fft_fftw.MULTIPLIER_PLANS) == 0


def test_lru_cache_calls_the_factory_once_per_miss():
    from phisim.spectral.cache import LRUCache

    made = []
    c = LRUCache(2)
    for k in "abab":
        c.get(k, lambda k=k: made.append(k) or k.upper())
    assert made == ["a", "b"] and c.get("c", lambda: "C") == "C" and "a" not in c and c.keys() == ["b", "c"]


@pytest.mark.skipif("pyfftw" not in ENGINES, reason="the routing belongs to the pyfftw engine")
def test_default_planner_routes_real_to_real_kinds_to_pocketfft():
    from phisim.spectral.pocket import use_pocket

    # deterministic default: every DCT/DST kind on pocketfft (no plans), also float64 powers of two
    assert use_pocket(torch.float64, ("dct2", "dct2"), (256, 256))
    # measured plans (opt-in) keep FFTW where it measured faster
    assert not use_pocket(torch.float64, ("dct2", "dct2"), (256, 256), "FFTW_MEASURE")
    assert use_pocket(torch.float64, ("dct2",), (96,), "FFTW_MEASURE")
