"""Bad input everywhere: every public function and CLI command answers with a typed PhisimError and a hint.

Each case names the call, the expected error class and a fragment of the message a user needs (what is
wrong, or what to do). Nothing here may give a raw Python/torch/h5py exception, a NaN result or a hang.
"""

from __future__ import annotations

import math
import os
import warnings

import h5py
import numpy as np
import pytest
import torch

import phisim as ps
from inverse.cli import main as cli_main
from inverse.problems import Method, get_problem
from inverse.train import train
from phisim.errors import (
    BoundaryError,
    FileFormatError,
    GridMismatchError,
    NonFiniteError,
    ParameterError,
    PhisimError,
    ShapeError,
)
from phisim.solvers import poisson

G = ps.Grid((8, 6))
G3 = ps.Grid((4, 4, 4))
W = ps.Boundary.create("wall", 2)
P = ps.Boundary.create("periodic", 2)
S = ps.CenteredGrid.zeros(G, W.for_scalar(), 2)
V = ps.StaggeredGrid.zeros(G, W, 2)
VP = ps.StaggeredGrid.zeros(G, P, 2)
R = torch.zeros(2, 8, 6)
NAN = float("nan")


def _ones_mask(v=1.0):
    return torch.full((8, 6), v)


CASES = [
    # ---- Grid ----
    ("grid-string-resolution", lambda: ps.Grid("64"), ParameterError, "int or a sequence"),
    ("grid-float-resolution", lambda: ps.Grid(64.0), ParameterError, "int or a sequence"),
    ("grid-none-resolution", lambda: ps.Grid(None), ParameterError, "sequence of ints"),
    ("grid-bool-resolution", lambda: ps.Grid(True), ParameterError, "int or a sequence"),
    ("grid-zero-cells", lambda: ps.Grid((0, 4)), ParameterError, ">= 1"),
    ("grid-negative-cells", lambda: ps.Grid((-4, 4)), ParameterError, ">= 1"),
    ("grid-fractional-cells", lambda: ps.Grid((4.5, 4)), ParameterError, "integers"),
    ("grid-four-axes", lambda: ps.Grid((2, 2, 2, 2)), ParameterError, "1, 2 or 3 axes"),
    ("grid-string-entry", lambda: ps.Grid((4, "a")), ParameterError, "sequence of ints"),
    ("grid-scalar-bounds", lambda: ps.Grid((4, 4), bounds=1.0), ParameterError, "one .lower, upper. pair"),
    ("grid-string-bounds", lambda: ps.Grid((4, 4), bounds="ab"), ParameterError, "bounds"),
    ("grid-bounds-count", lambda: ps.Grid((4, 4), bounds=[(0, 1)]), ParameterError, "2 axes"),
    ("grid-inverted-bounds", lambda: ps.Grid((4,), bounds=[(1, 0)]), ParameterError, "upper > lower"),
    ("grid-nan-bounds", lambda: ps.Grid((4,), bounds=[(0, NAN)]), ParameterError, "finite"),
    ("grid-string-bound-entry", lambda: ps.Grid((4, 4), bounds=[(0, 1), "x"]), ParameterError, "neither a size"),
    ("grid-tiny-cells", lambda: ps.Grid((4,), bounds=[(0, 1e-30)]), ParameterError, "rescale"),
    ("grid-huge-cells", lambda: ps.Grid((4,), bounds=[(0, 1e30)]), ParameterError, "rescale"),
    # ---- boundaries ----
    ("dirichlet-string", lambda: ps.Dirichlet("hot"), BoundaryError, "number"),
    ("dirichlet-nan", lambda: ps.Dirichlet(NAN), NonFiniteError, "finite"),
    ("dirichlet-inf", lambda: ps.Dirichlet(math.inf), NonFiniteError, "finite"),
    ("dirichlet-nan-tensor", lambda: ps.Dirichlet(torch.tensor([NAN, 0.0])), NonFiniteError, "NaN"),
    ("dirichlet-complex", lambda: ps.Dirichlet(torch.ones(2, dtype=torch.complex64)), BoundaryError, "real"),
    ("dirichlet-none", lambda: ps.Dirichlet(None), BoundaryError, "number"),
    ("dirichlet-object-array", lambda: ps.Dirichlet(np.array([object()])), BoundaryError, "real numeric"),
    ("dirichlet-empty-tuple", lambda: ps.Dirichlet(()), BoundaryError, "empty"),
    ("neumann-string", lambda: ps.Neumann("cold"), BoundaryError, "number"),
    ("neumann-nan-tuple", lambda: ps.Neumann((0.0, NAN)), NonFiniteError, "NaN"),
    ("noslip-scalar-velocity", lambda: ps.NoSlipWall(velocity=5.0), BoundaryError, "vector"),
    ("noslip-string-velocity", lambda: ps.NoSlipWall(velocity="fast"), BoundaryError, "tuple"),
    ("noslip-nan-velocity", lambda: ps.NoSlipWall(velocity=(NAN, 0.0)), NonFiniteError, "NaN"),
    ("noslip-wrong-length", lambda: ps.Boundary.create(ps.NoSlipWall((1.0, 0.0, 0.0)), 2), BoundaryError,
     "3 entries for a 2-D"),
    ("dirichlet-vector-wrong-length", lambda: ps.Boundary.create(ps.Dirichlet((1.0, 2.0, 3.0)), 2), BoundaryError,
     "one per axis"),
    ("boundary-unknown-name", lambda: ps.Boundary.create("sticky", 2), BoundaryError, "known names"),
    ("boundary-one-sided-periodic", lambda: ps.Boundary.create([("periodic", "wall"), "wall"], 2), BoundaryError,
     "both sides"),
    ("boundary-wrong-axis-count", lambda: ps.Boundary.create(["wall"] * 3, 2), BoundaryError, "3 entries"),
    ("boundary-bad-rank", lambda: ps.Boundary.create("wall", 0), BoundaryError, "rank"),
    ("boundary-mapping-missing-axis", lambda: ps.Boundary.create({"x": "wall"}, 2), BoundaryError, "misses"),
    ("boundary-mapping-bad-key", lambda: ps.Boundary.create({"x": "wall", "q": "wall"}, 2), BoundaryError, "key"),
    ("boundary-raw-sides", lambda: ps.Boundary(("wall", "wall")), BoundaryError, "pair of conditions"),
    ("boundary-pair-length", lambda: ps.Boundary.create([("wall", "wall", "wall"), "wall"], 2), BoundaryError,
     "lower, upper"),
    # ---- fields ----
    ("centered-complex", lambda: ps.CenteredGrid(torch.zeros(1, 8, 6, dtype=torch.complex64), G, W), ParameterError,
     "real"),
    ("centered-object-array", lambda: ps.CenteredGrid(np.empty((1, 8, 6), dtype=object), G, W), ParameterError,
     "real numeric"),
    ("centered-string-values", lambda: ps.CenteredGrid("zeros", G, W), ParameterError, "tensor or array"),
    ("centered-wrong-shape", lambda: ps.CenteredGrid(torch.zeros(1, 6, 8), G, W), ShapeError, "batch axis"),
    ("centered-no-batch", lambda: ps.CenteredGrid(torch.zeros(8, 6), G, W), ShapeError, r"values\[None\]"),
    ("centered-not-a-grid", lambda: ps.CenteredGrid(torch.zeros(1, 8, 6), (8, 6), W), GridMismatchError, "Grid"),
    ("centered-zeros-negative-batch", lambda: ps.CenteredGrid.zeros(G, W, -1), ParameterError, "batch_size"),
    ("centered-zeros-float-batch", lambda: ps.CenteredGrid.zeros(G, W, 1.5), ParameterError, "batch_size"),
    ("staggered-zeros-negative-batch", lambda: ps.StaggeredGrid.zeros(G, W, -1), ParameterError, "batch_size"),
    ("staggered-wrong-count", lambda: ps.StaggeredGrid((torch.zeros(1, 9, 6),), G, W), ShapeError, "sequence of 2"),
    ("staggered-wrong-face-shape", lambda: ps.StaggeredGrid((torch.zeros(1, 8, 6), torch.zeros(1, 8, 7)), G, W),
     ShapeError, "resolution \\+ 1"),
    ("field-add-wrong-shape", lambda: S + torch.zeros(3, 5), ShapeError, "broadcast"),
    ("field-add-string", lambda: S + "1", ParameterError, "cannot add"),
    ("field-add-other-grid", lambda: S + ps.CenteredGrid.zeros(ps.Grid((8, 7)), W, 2), GridMismatchError,
     "different grids"),
    ("field-add-centered-staggered", lambda: S + V, GridMismatchError, "resample"),
    ("field-add-other-boundary", lambda: V + VP, GridMismatchError, "with_boundary"),
    ("field-add-other-device", lambda: S + ps.CenteredGrid.zeros(G, W.for_scalar(), 2, device="meta"),
     GridMismatchError, "different devices"),
    ("field-mul-wrong-batch", lambda: V * torch.ones(3, 1, 1), ShapeError, "broadcast"),
    # ---- differential operators ----
    ("laplace-tensor", lambda: ps.laplace(R), ShapeError, "stencil_laplacian"),
    ("laplace-none", lambda: ps.laplace(None), ShapeError, "CenteredGrid"),
    ("gradient-vector", lambda: ps.gradient(V), ShapeError, "scalar"),
    ("gradient-tensor", lambda: ps.gradient(R), ShapeError, "scalar"),
    ("divergence-scalar", lambda: ps.divergence(S), ShapeError, ""),
    ("curl-tensor", lambda: ps.curl(R), ShapeError, "CenteredGrid"),
    # ---- checks ----
    ("check-dt-negative", lambda: ps.check_dt(-1.0), ParameterError, "backwards"),
    ("check-dt-string", lambda: ps.check_dt("0.1"), ParameterError, "number"),
    ("check-dt-nan", lambda: ps.check_dt(NAN), ParameterError, "finite"),
    ("check-nonnegative-string", lambda: ps.check_nonnegative("0.1", "viscosity"), ParameterError, "viscosity"),
    ("check-positive-zero", lambda: ps.check_positive(0, "cfl"), ParameterError, "> 0"),
    ("check-finite-nan", lambda: ps.check_finite(torch.tensor([NAN]), "state"), NonFiniteError, "state"),
    ("check-device-cuda-missing", lambda: ps.check_device("cuda:99"), ParameterError, "CUDA|device"),
    ("check-device-garbage", lambda: ps.check_device("gpu-please"), ParameterError, "unknown device"),
    # ---- Poisson ----
    ("poisson-dx-none", lambda: ps.spectral_poisson_solve(R, None, "dirichlet"), ParameterError, "dx"),
    ("poisson-dx-string", lambda: ps.spectral_poisson_solve(R, "1", "dirichlet"), ParameterError, "dx"),
    ("poisson-dx-negative", lambda: ps.spectral_poisson_solve(R, -1.0, "dirichlet"), ParameterError, "> 0"),
    ("poisson-dx-tiny", lambda: ps.spectral_poisson_solve(R, 1e-30, "dirichlet"), ParameterError, "rescale"),
    ("poisson-dx-count", lambda: ps.spectral_poisson_solve(R, (1.0, 1.0, 1.0), "dirichlet"), ParameterError,
     "3 entries"),
    ("poisson-empty-rhs", lambda: ps.spectral_poisson_solve(torch.zeros(1, 0, 4), 1.0, "dirichlet"), ShapeError,
     "empty"),
    ("poisson-empty-batch", lambda: ps.spectral_poisson_solve(torch.zeros(0, 4, 4), 1.0, "dirichlet"), ShapeError,
     "empty"),
    ("poisson-int-rhs", lambda: ps.spectral_poisson_solve(torch.zeros(1, 4, 4, dtype=torch.int64), 1.0, "dirichlet"),
     ParameterError, "float32 or float64"),
    ("poisson-numpy-rhs", lambda: ps.spectral_poisson_solve(np.zeros((1, 4, 4)), 1.0, "dirichlet"), ParameterError,
     "torch.Tensor"),
    ("poisson-no-batch-1d", lambda: ps.spectral_poisson_solve(torch.zeros(4), 1.0, "dirichlet"), ShapeError,
     "batch axis"),
    ("poisson-nan-rhs", lambda: ps.spectral_poisson_solve(torch.full((1, 4, 4), NAN), 1.0, "dirichlet"),
     NonFiniteError, "NaN"),
    ("poisson-unknown-kind", lambda: ps.spectral_poisson_solve(R, 1.0, "robin"), BoundaryError, "unknown"),
    ("poisson-incompatible", lambda: ps.spectral_poisson_solve(torch.ones(1, 4, 4), 1.0, "neumann"), ParameterError,
     "incompatible|mean"),
    ("poisson-nan-boundary-value", lambda: poisson.stencil_laplacian(R, 1.0, "dirichlet", [(NAN, 0.0), None]),
     NonFiniteError, "boundary value"),
    ("poisson-inf-boundary-value-solve",
     lambda: ps.spectral_poisson_solve(R, 1.0, "dirichlet", [(math.inf, 0.0), None]), NonFiniteError, "NaN or Inf"),
    ("poisson-string-boundary-value", lambda: poisson.stencil_laplacian(R, 1.0, "dirichlet", [("hot", 0.0), None]),
     BoundaryError, "number"),
    ("solve-poisson-nan-dirichlet-field",
     lambda: ps.solve_poisson(ps.CenteredGrid(R, G, ps.Dirichlet(torch.full((1, 1, 6), NAN))), ), NonFiniteError,
     "NaN"),
    ("masked-half-mask", lambda: ps.masked_poisson_solve(torch.randn(1, 8, 6), _ones_mask(0.5), 1.0, "dirichlet"),
     ParameterError, "0/1"),
    ("masked-mask-shape", lambda: ps.masked_poisson_solve(torch.randn(1, 8, 6), torch.ones(6, 8), 1.0), ShapeError,
     "mask must have shape"),
    ("masked-no-fluid", lambda: ps.masked_poisson_solve(torch.randn(1, 8, 6), _ones_mask(0.0), 1.0, "dirichlet"),
     ParameterError, "no fluid"),
    ("masked-string-mask", lambda: ps.masked_poisson_solve(torch.randn(1, 8, 6), "all", 1.0), ParameterError, "mask"),
    ("masked-bad-preconditioner", lambda: ps.masked_poisson_solve(R, _ones_mask(), preconditioner="ilu"),
     ParameterError, "spectral"),
    ("masked-closed-pocket", lambda: _pocket_case(), ParameterError, "pocket"),
    # ---- linalg ----
    ("solve-negative-rtol", lambda: ps.Solve(rtol=-1.0), ParameterError, "rtol"),
    ("solve-zero-tolerances", lambda: ps.Solve(rtol=0, atol=0), ParameterError, "never be met"),
    ("solve-string-max-iter", lambda: ps.Solve(max_iter="10"), ParameterError, "max_iter"),
    ("solve-widen-not-bool", lambda: ps.Solve(widen_tolerance=1), ParameterError, "True or False"),
    # ---- diffusion / heat ----
    ("diffuse-huge-viscosity-dt", lambda: ps.diffuse(S, 1e300, viscosity=1e300), ParameterError, "overflows"),
    ("heat-huge-viscosity-dt", lambda: ps.fourier_heat(torch.zeros(1, 8, 8), 1e300, viscosity=1e300), ParameterError,
     "overflows"),
    ("diffuse-string-viscosity", lambda: ps.diffuse(S, 0.1, viscosity="0.1"), ParameterError, "viscosity"),
    ("diffuse-negative-dt", lambda: ps.diffuse(S, -0.1, viscosity=0.1), ParameterError, "dt"),
    ("diffuse-unknown-method", lambda: ps.diffuse(S, 0.1, viscosity=0.1, method="magic"), ParameterError, "method"),
    ("diffuse-tensor", lambda: ps.diffuse(R, 0.1, viscosity=0.1), PhisimError, "CenteredGrid"),
    ("explicit-limit-string-viscosity", lambda: ps.explicit_stability_limit(1.0, "a"), ParameterError, "viscosity"),
    # ---- fluid ----
    ("cfl-string", lambda: ps.cfl_dt(V, "0.5"), ParameterError, "cfl"),
    ("cfl-zero", lambda: ps.cfl_dt(V, 0.0), ParameterError, "cfl"),
    ("cfl-max-dt-string", lambda: ps.cfl_dt(V, 0.5, max_dt="1"), ParameterError, "max_dt"),
    ("normalize-energy-negative", lambda: ps.normalize_energy(V, -1.0), ParameterError, ">= 0"),
    ("normalize-energy-nan", lambda: ps.normalize_energy(V, NAN), ParameterError, "finite"),
    ("obstacle-box-nan-corner", lambda: ps.Obstacle.box((NAN, 1.0), (3.0, 3.0)), ParameterError, "lower <= upper"),
    ("obstacle-box-inverted", lambda: ps.Obstacle.box((3.0, 1.0), (1.0, 3.0)), ParameterError, "lower <= upper"),
    ("obstacle-sphere-negative", lambda: ps.Obstacle.sphere((3.0, 3.0), -1.0), ParameterError, "radius"),
    ("buoyancy-nan-strength", lambda: ps.buoyancy(V, S, 0.1, strength=NAN), ParameterError, "buoyancy strength"),
    ("step-nan-buoyancy", lambda: ps.step(ps.FluidState(V, S), 0.1, buoyancy_strength=NAN), ParameterError,
     "buoyancy strength"),
    ("step-string-viscosity", lambda: ps.step(ps.FluidState(V, S), 0.1, viscosity="0.1"), ParameterError,
     "viscosity"),
    ("step-negative-dt", lambda: ps.step(ps.FluidState(V, S), -0.1), ParameterError, "dt"),
    ("projection-tensor", lambda: ps.make_incompressible(R), PhisimError, ""),
    ("kinetic-energy-tensor", lambda: ps.kinetic_energy(R), PhisimError, ""),
    # ---- FFT settings ----
    ("fft-unknown-engine", lambda: ps.set_fft_settings(engine="cufft"), ParameterError, "engine"),
    ("fft-zero-threads", lambda: ps.FFTSettings(threads=0), ParameterError, "threads"),
    ("fft-unknown-planner", lambda: ps.FFTSettings(planner_effort="FFTW_FAST"), ParameterError, "planner"),
    # ---- I/O ----
    ("writer-negative-batch", lambda: _writer(batch_size=-1), ParameterError, "batch_size"),
    ("writer-no-fields", lambda: _writer(fields={}), ParameterError, "at least one field"),
    ("writer-unknown-kind", lambda: _writer(fields={"a": "tensor"}), ParameterError, "kind"),
    ("writer-bad-field-name", lambda: _writer(fields={"a/b": "scalar"}), ParameterError, "field name"),
    ("writer-string-parameter", lambda: _writer(parameters={"nu": "small"}), ParameterError, "config="),
    ("writer-int-dtype", lambda: _writer(dtype=torch.int32), ParameterError, "floating"),
    ("writer-compression", lambda: _writer(compression_level=11), ParameterError, "0..9"),
    ("writer-unserialisable-config", lambda: _writer(config={"f": object()}), ParameterError, "JSON"),
    ("writer-grid-tuple", lambda: ps.SimulationWriter("x.h5", (8, 6), "wall", dataset_name="d",
                                                      fields={"a": "scalar"}, batch_size=1), ParameterError, "Grid"),
    ("writer-output-is-folder", lambda: _writer(path="."), FileFormatError, "directory"),
    ("writer-append-wrong-shape", lambda: _append(a=np.zeros((1, 6, 8))), ShapeError, "shape"),
    ("writer-append-missing-field", lambda: _append(), ParameterError, "missing"),
    ("writer-append-complex", lambda: _append(a=torch.zeros(1, 8, 6, dtype=torch.complex64)), ShapeError, "complex"),
    ("writer-append-nan-time", lambda: _append(time=NAN, a=np.zeros((1, 8, 6))), ParameterError, "time"),
    ("writer-append-string-time", lambda: _append(time="t0", a=np.zeros((1, 8, 6))), ParameterError, "time"),
    ("read-missing-file", lambda: ps.read_simulation("no/such/file.h5"), FileFormatError, "does not exist"),
    ("read-folder", lambda: ps.read_simulation("."), FileFormatError, "directory"),
    ("read-text-file", lambda: ps.read_simulation(_text_file()), FileFormatError, "not a readable HDF5"),
    ("read-named-pipe", lambda: ps.read_simulation(_fifo()), FileFormatError, "not a regular file"),
    ("read-training-pipe", lambda: ps.read_training(_fifo()), FileFormatError, "not a regular file"),
    ("read-malformed-attrs", lambda: ps.read_simulation(_malformed_attrs()), FileFormatError, "malformed|damaged"),
    ("read-empty-hdf5", lambda: ps.read_simulation(_empty_h5()), FileFormatError, "dataset_name"),
    ("log-bad-method", lambda: ps.TrainingLog(_tmp("log.h5"), "a/b"), ParameterError, "method"),
    ("log-target-int", lambda: ps.TrainingLog(3, "adam"), ParameterError, "target"),
    ("log-non-hdf5-file", lambda: ps.TrainingLog(_text_file(), "adam"), FileFormatError, "not an HDF5 file"),
    ("log-append-no-values", lambda: _log().append(0), ParameterError, "at least one value"),
    ("log-append-string-value", lambda: _log().append(0, loss="low"), ParameterError, "not a number"),
    ("log-append-tensor-value", lambda: _log().append(0, loss=torch.ones(3)), ParameterError, "one number"),
    ("recover-journal-garbage", lambda: ps.recover_file(_garbage_journal()), FileFormatError, "not a phisim journal"),
    # ---- training ----
    ("method-negative-lr", lambda: Method("m", "physics", lr=-1e-3), ParameterError, "lr"),
    ("method-zero-lr", lambda: Method("m", "physics", lr=0.0), ParameterError, "lr"),
    ("method-nan-eta", lambda: Method("m", "physgrad", eta=NAN), ParameterError, "eta"),
    ("method-string-lr", lambda: Method("m", "physics", lr="fast"), ParameterError, "lr"),
    ("train-unknown-problem", lambda: train("nope", "adam", iterations=1), PhisimError, ""),
    ("train-unknown-method", lambda: train("sine", "nope", iterations=1), ParameterError, "no method"),
    ("train-negative-batch", lambda: train("sine", "adam", iterations=1, batch_size=-1), ParameterError,
     "batch_size"),
    ("train-float-iterations", lambda: train("sine", "adam", iterations=1.5), ParameterError, "iterations"),
    ("train-cuda-missing", lambda: train("sine", "adam", iterations=1, device="cuda:99"), ParameterError,
     "CUDA|device"),
    ("train-out-folder", lambda: train("sine", "adam", iterations=1, out="."), FileFormatError, "directory"),
    ("train-out-text", lambda: train("sine", "adam", iterations=1, out=_text_file()), FileFormatError,
     "not an HDF5 file"),
    ("train-resume-no-out", lambda: train("sine", "adam", iterations=1, resume=True), ParameterError, "out="),
    ("problem-bad-resolution", lambda: train(get_problem("poisson", resolution=(0, 4)), "pg", iterations=1),
     ParameterError, ">= 1"),
]

_TMP = {}


def _tmp(name: str):
    return _TMP["dir"] / name


def _text_file():
    p = _tmp("notes.txt")
    p.write_text("this is not HDF5\n")
    return p


def _fifo():
    p = _tmp("pipe.h5")
    if not p.exists():
        os.mkfifo(p)
    return p


def _malformed_attrs():
    p = _tmp("foreign.h5")
    with h5py.File(p, "w") as f:
        f.attrs["dataset_name"] = "foreign"
        f.attrs["grid_type"] = "cartesian"
        f.attrs["n_spatial_dims"] = "two"
        f.attrs["n_trajectories"] = 1
    return p


def _empty_h5():
    p = _tmp("empty.h5")
    h5py.File(p, "w").close()
    return p


def _garbage_journal():
    p = _tmp("g.h5")
    (_tmp("g.h5.journal")).write_bytes(b"garbage" * 10)
    return p


def _writer(path=None, **kw):
    args = dict(dataset_name="d", fields={"a": "scalar"}, batch_size=1)
    args.update(kw)
    return ps.SimulationWriter(path or _tmp("w.h5"), G, "wall", **args)


def _append(time=0.0, **fields):
    with _writer() as w:
        w.append(time, **fields)


def _log():
    return ps.TrainingLog(_tmp("tl.h5"), "adam")


def _pocket_case():
    mask = torch.ones(8, 6, dtype=torch.bool)
    mask[3, :] = False  # a wall of obstacle cells splits the closed box into two pockets
    rhs = torch.zeros(1, 8, 6, dtype=torch.float64)
    rhs[0, 0, 0], rhs[0, 7, 5] = 1.0, -1.0  # globally compatible, each pocket is not
    return ps.masked_poisson_solve(rhs, mask, 1.0, "neumann", solve=ps.Solve(max_iter=400))


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    _TMP["dir"] = tmp_path
    monkeypatch.chdir(tmp_path)
    yield


def test_enough_distinct_cases():
    names = [c[0] for c in CASES]
    assert len(set(names)) == len(names) and len(names) >= 100


@pytest.mark.parametrize("name, call, error, match", CASES, ids=[c[0] for c in CASES])
def test_bad_input_gives_typed_error(name, call, error, match):
    if name.startswith(("check-device-cuda", "train-cuda")) and torch.cuda.device_count() > 99:
        pytest.skip("a machine with 100 GPUs")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(error, match=match or None) as info:
            call()
    assert isinstance(info.value, PhisimError)
    assert len(str(info.value)) > 15  # a message a user can act on, not a bare name


# ---- command line -------------------------------------------------------------------------------------

CLI_CASES = [
    ("info-missing", ["info", "missing.h5"], "does not exist"),
    ("info-folder", ["info", "."], "directory"),
    ("info-text", ["info", "notes.txt"], "not a readable HDF5"),
    ("info-pipe", ["info", "pipe.h5"], "not a regular file"),
    ("train-unknown-problem", ["train", "nope", "adam", "--iterations", "1"], "problem"),
    ("train-unknown-method", ["train", "sine", "nope", "--iterations", "1"], "no method"),
    ("train-negative-iterations", ["train", "sine", "adam", "--iterations", "-3"], "iterations"),
    ("train-zero-batch", ["train", "sine", "adam", "--batch-size", "0"], "batch-size"),
    ("train-cuda-missing", ["train", "sine", "adam", "--iterations", "1", "--device", "cuda:99"], "CUDA|device"),
    ("train-bad-device", ["train", "sine", "adam", "--iterations", "1", "--device", "warp-drive"], "device"),
    ("train-out-is-folder", ["train", "sine", "adam", "--iterations", "1", "--out", "."], "directory"),
    ("train-out-not-hdf5", ["train", "sine", "adam", "--iterations", "1", "--out", "notes.txt"], "not an HDF5 file"),
    ("train-bad-resolution", ["train", "poisson", "pg", "--iterations", "1", "--resolution", "0", "4"],
     "resolution"),
    ("train-negative-checkpoint", ["train", "sine", "adam", "--checkpoint-every", "-1"], "checkpoint"),
    ("compare-plot-folder", ["compare", "sine", "adam", "--iterations", "1", "--plot", "."], "directory"),
    ("compare-unknown-method", ["compare", "sine", "adam", "nope", "--iterations", "1"], "no method"),
]


@pytest.mark.parametrize("name, argv, match", CLI_CASES, ids=[c[0] for c in CLI_CASES])
def test_cli_user_error_is_one_line_without_traceback(name, argv, match, capsys):
    _text_file()
    _fifo()
    code = cli_main(argv)
    out = capsys.readouterr()
    assert code == 2, out
    assert "Traceback" not in out.err and out.err.startswith("phisim: error:")
    assert len(out.err.strip().splitlines()) == 1
    import re

    assert re.search(match, out.err), out.err
    assert not any(p.suffix == ".ckpt" for p in _TMP["dir"].iterdir())


def test_cli_checks_output_before_training(capsys, monkeypatch):
    """A bad --out fails before the first iteration, not after training finished."""
    import importlib

    train_module = importlib.import_module("inverse.train")

    calls = []
    monkeypatch.setattr(train_module, "_step", lambda *a, **k: calls.append(1))
    _text_file()
    assert cli_main(["train", "sine", "adam", "--iterations", "5", "--out", "notes.txt"]) == 2
    assert calls == []


def test_cli_unexpected_error_is_one_line(capsys, monkeypatch):
    import inverse.cli as cli

    monkeypatch.delenv("PHISIM_DEBUG", raising=False)
    monkeypatch.setattr(cli, "describe_file", lambda p: (_ for _ in ()).throw(RuntimeError("boom")))
    assert cli_main(["info", "x.h5"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and "boom" in err and "PHISIM_DEBUG" in err


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_asked_for_without_cuda(capsys):
    with pytest.raises(ParameterError, match="CUDA is not available"):
        ps.check_device("cuda")
    with pytest.raises(ParameterError, match="CUDA is not available"):
        train("sine", "adam", iterations=1, device="cuda")
    assert cli_main(["train", "sine", "adam", "--iterations", "1", "--device", "cuda"]) == 2
    assert "CUDA is not available" in capsys.readouterr().err
