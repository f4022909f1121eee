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
from inverse import cli_checks
from inverse.cli import main as cli_main
from inverse.problems import Method, get_problem
from inverse.train import train
from phisim.checks import existing_file
from phisim.errors import (
    BoundaryError,
    FileFormatError,
    GridMismatchError,
    NonFiniteError,
    ParameterError,
    PhisimError,
    ShapeError,
)
from phisim.io.h5util import open_for_read
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
    ("read-folder", lambda: ps.read_simulation("."), FileFormatError, "is a folder, not a file"),
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
    ("info-folder", ["info", "."], "file . is a folder, not a file"),
    ("info-text", ["info", "notes.txt"], "file notes.txt is not an HDF5 file"),
    ("info-pipe", ["info", "pipe.h5"], "not a regular file"),
    ("train-unknown-problem", ["train", "nope", "adam", "--iterations", "1"], "problem"),
    ("train-unknown-method", ["train", "sine", "nope", "--iterations", "1"], "no method"),
    ("train-negative-iterations", ["train", "sine", "adam", "--iterations", "-3"], "iterations"),
    ("train-zero-batch", ["train", "sine", "adam", "--batch-size", "0"], "batch-size"),
    ("train-cuda-missing", ["train", "sine", "adam", "--iterations", "1", "--device", "cuda:99"], "CUDA|device"),
    ("train-bad-device", ["train", "sine", "adam", "--iterations", "1", "--device", "warp-drive"], "device"),
    ("train-out-is-folder", ["train", "sine", "adam", "--iterations", "1", "--out", "."],
     "output file . is a folder, not a file"),
    ("train-out-not-hdf5", ["train", "sine", "adam", "--iterations", "1", "--out", "notes.txt"], "not an HDF5 file"),
    ("train-bad-resolution", ["train", "poisson", "pg", "--iterations", "1", "--resolution", "0", "4"],
     "resolution"),
    ("train-negative-checkpoint", ["train", "sine", "adam", "--checkpoint-every", "-1"], "checkpoint"),
    ("compare-plot-folder", ["compare", "sine", "adam", "--iterations", "1", "--plot", "."],
     r"--plot file \. is a folder, not a file; give a file name such as curves.png"),
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


def test_cli_unexpected_error_is_one_line(capsys, monkeypatch, tmp_path):
    import h5py

    import inverse.cli as cli

    monkeypatch.delenv("PHISIM_DEBUG", raising=False)
    monkeypatch.setattr(cli, "describe_file", lambda p: (_ for _ in ()).throw(RuntimeError("boom")))
    h5py.File(tmp_path / "x.h5", "w").close()  # passes the path checks; the command itself then fails
    assert cli_main(["info", str(tmp_path / "x.h5")]) == 1
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


# ==== bad input by class (issue 27, item 5) =============================================================
# One parametrized test per class of bad input, each run across the public functions the class applies to.
# Arguments are checked by the helpers of phisim/checks.py (check_number, check_int, check_seed, check_bool,
# check_choice, check_batch_compatible, check_nonempty_batch, check_callable_output).

import importlib  # noqa: E402
import re  # noqa: E402

from inverse import hig as _hig  # noqa: E402
from inverse import local_solvers as _ls  # noqa: E402
from inverse import nets as _nets  # noqa: E402
from inverse import operators as _ops  # noqa: E402
from inverse.custom import CallableOperator  # noqa: E402
from phisim.simulate import noise as _noise  # noqa: E402
from phisim.solvers.linalg import cg as _cg  # noqa: E402
from phisim.spectral.settings import FFTSettings  # noqa: E402

_pg = importlib.import_module("inverse.physgrad")
_NET = torch.nn.Linear(2, 2)


def _s(b, boundary=None):
    return ps.CenteredGrid.zeros(G, boundary or W.for_scalar(), b)


def _v(b):
    return ps.StaggeredGrid.zeros(G, W, b)


# ---- class 1: two operands whose batch sizes differ (2 vs 3) -------------------------------------------
BATCH_MISMATCH = [
    ("centered+centered", lambda: _s(2) + _s(3)),
    ("centered-centered-reversed", lambda: _s(3).__rsub__(_s(2))),
    ("vector*scalar", lambda: ps.CenteredGrid.zeros(G, W, 2, channels=2) * ps.CenteredGrid.zeros(G, W, 3)),
    ("staggered+staggered", lambda: _v(2) + _v(3)),
    ("staggered*staggered", lambda: _v(3) * _v(2)),
    ("centered+tensor", lambda: _s(2) + torch.zeros(3, 8, 6)),
    ("staggered*tensor", lambda: _v(2) * torch.ones(3, 1, 1)),
    ("scalar+tensor-with-extra-axis", lambda: _s(2) + torch.zeros(3, 2, 8, 6)),
    ("advect-velocity", lambda: ps.advect(_s(2), _v(3), 0.1)),
    ("sample-padded-index", lambda: ps.sample_padded(torch.zeros(2, 1, 8, 6), torch.zeros(3, 4, 2))),
    ("rectangles-corners", lambda: _noise.rectangles(G, torch.zeros(2, 2), torch.ones(3, 2))),
    ("vortex-centre-strength", lambda: _noise.gaussian_vortex(G, torch.zeros(2, 2), torch.ones(3), 1.0)),
    ("uniform-velocity-batch", lambda: _noise.uniform_velocity(G, torch.zeros(2, 2), batch_size=3)),
    ("cg-x0-rhs", lambda: _cg(lambda x: x, torch.ones(2, 4), torch.zeros(3, 4))),
    ("operator-local-inverse", lambda: _ops.ScaleToy().local_inverse(torch.ones(3, 2), torch.ones(2, 2))),
    ("solver-operator", lambda: _ls.SolverOperator(lambda x: x, _ls.GradientStepSolver()).local_inverse(
        torch.ones(3, 2), torch.ones(2, 2))),
    ("local-solver", lambda: _ls.NewtonSolver()(lambda x: x, torch.ones(3, 2), torch.ones(2, 2))),
    ("physical-update", lambda: _pg.physical_update(torch.ones(2, 2), torch.ones(3, 2), _ops.ScaleToy())),
    ("physical-gradient-loss", lambda: _pg.physical_gradient_loss(torch.ones(2, 2), torch.ones(3, 2),
                                                                  _ops.ScaleToy())),
    ("hig-targets", lambda: _hig.HIG(_NET).step(torch.ones(2, 2), torch.ones(3, 2))),
    ("hig-physics-args", lambda: _hig.HIG(_NET, physics=lambda o, s: o * s).step(
        torch.ones(2, 2), torch.ones(2, 2), physics_args=(torch.ones(3, 2),))),
    ("buoyancy-marker", lambda: ps.buoyancy(_v(2), _s(3), 0.1, strength=1.0)),
    ("normalize-energy-target", lambda: ps.normalize_energy(_v(2), torch.ones(3))),
    ("relative-divergence-reference", lambda: ps.relative_divergence(_v(2), reference=_v(3))),
    ("projection-pressure-guess", lambda: ps.make_incompressible(_v(2), pressure_guess=torch.zeros(3, 8, 6))),
]


@pytest.mark.parametrize("call", [c[1] for c in BATCH_MISMATCH], ids=[c[0] for c in BATCH_MISMATCH])
def test_batch_sizes_that_differ_give_shape_error_naming_both(call):
    with pytest.raises(ShapeError) as info:
        call()
    msg = str(info.value)
    assert re.search(r"\b2\b", msg) and re.search(r"\b3\b", msg), msg


BATCH_BROADCAST = [  # the documented rule's other half: a batch of 1 is shared by every sample of the other
    ("centered+centered", lambda: (_s(1) + _s(3)).batch_size),
    ("staggered*staggered", lambda: (_v(3) * _v(1)).batch_size),
    ("cg-x0", lambda: _cg(lambda x: 2 * x, torch.ones(3, 4), torch.zeros(1, 4)).shape[0]),
    ("operator-target", lambda: _ops.ScaleToy().local_inverse(torch.ones(1, 2), torch.ones(3, 2)).shape[0]),
    ("local-solver-target", lambda: _ls.GradientStepSolver()(lambda x: x, torch.ones(1, 2), torch.ones(3, 2)).shape[0]),
    ("physical-update", lambda: _pg.physical_update(torch.ones(3, 2), torch.ones(1, 2), _ops.ScaleToy())[0].shape[0]),
    ("hig-physics-args", lambda: _hig.per_sample_jacobian(_NET, torch.ones(3, 2), lambda o, s: o * s,
                                                          (torch.ones(1, 2),)).shape[0] // 2),
]


@pytest.mark.parametrize("call", [c[1] for c in BATCH_BROADCAST], ids=[c[0] for c in BATCH_BROADCAST])
def test_batch_of_one_broadcasts(call):
    assert call() == 3


# ---- class 2: a string, None, a list, NaN or an out-of-range integer where a number is expected --------
# (function of the bad value, the argument's name in the message, kind: 'int', 'float', 'int?', 'float?'
# (None allowed), 'pos' (a finite number > 0 where a huge int is fine), 'seed')
NUMBER_ARGS = [
    # phisim: fields, noise, solver and FFT settings
    ("centered-zeros-batch", lambda v: ps.CenteredGrid.zeros(G, W, v), "batch_size", "int"),
    ("centered-zeros-channels", lambda v: ps.CenteredGrid.zeros(G, W, 1, channels=v), "channels", "int?"),
    ("staggered-zeros-batch", lambda v: ps.StaggeredGrid.zeros(G, W, v), "batch_size", "int"),
    ("noise-seed", lambda v: _noise.spectral_noise(G, seed=v), "seed", "seed"),
    ("noise-batch", lambda v: _noise.spectral_noise(G, v), "batch_size", "int"),
    ("noise-channels", lambda v: _noise.spectral_noise(G, channels=v), "channels", "int?"),
    ("noise-power", lambda v: _noise.spectral_noise(G, power=v), "power", "float"),
    ("noise-scale", lambda v: _noise.spectral_noise(G, scale=v), "scale", "pos"),
    ("noise-cutoff", lambda v: _noise.spectral_noise(G, cutoff=v), "cutoff", "float"),
    ("rectangles-seed", lambda v: _noise.random_rectangles(G, seed=v), "seed", "seed"),
    ("rectangles-batch", lambda v: _noise.random_rectangles(G, v), "batch_size", "int"),
    ("rectangles-count", lambda v: _noise.random_rectangles(G, count=(1, v)), "count", "int"),
    ("rectangles-half-size", lambda v: _noise.random_rectangles(G, max_half_size=v), "max_half_size", "float"),
    ("rectangles-margin", lambda v: _noise.random_rectangles(G, margin=v), "margin", "float"),
    ("rectangles-strength", lambda v: _noise.random_rectangles(G, strength=(0.0, v)), "strength", "float"),
    ("vortex-sigma", lambda v: _noise.gaussian_vortex(G, (1.0, 1.0), 1.0, v), "sigma", "pos"),
    ("vortex-axis", lambda v: _noise.gaussian_vortex(G3, (1.0, 1.0, 1.0), 1.0, 1.0, axis=v), "axis", "int"),
    ("vortex-batch", lambda v: _noise.gaussian_vortex(G, (1.0, 1.0), 1.0, 1.0, batch_size=v), "batch_size", "int?"),
    ("uniform-batch", lambda v: _noise.uniform_velocity(G, (1.0, 0.0), batch_size=v), "batch_size", "int?"),
    ("solve-rtol", lambda v: ps.Solve(rtol=v), "rtol", "float"),
    ("solve-atol", lambda v: ps.Solve(atol=v), "atol", "float"),
    ("solve-refine-rtol", lambda v: ps.Solve(refine_rtol=v), "refine_rtol", "float"),
    ("solve-max-iter", lambda v: ps.Solve(max_iter=v), "max_iter", "int?"),
    ("solve-max-refine", lambda v: ps.Solve(max_refine=v), "max_refine", "int"),
    ("solve-stagnation", lambda v: ps.Solve(stagnation_window=v), "stagnation_window", "int"),
    ("solve-check-every", lambda v: ps.Solve(check_every=v), "check_every", "int?"),
    ("fft-threads", lambda v: FFTSettings(threads=v), "threads", "int"),
    ("fft-plan-cache", lambda v: FFTSettings(plan_cache_size=v), "plan_cache_size", "int"),
    ("fft-transpose-bytes", lambda v: FFTSettings(transpose_bytes=v), "transpose_bytes", "int"),
    ("fft-wall-transpose", lambda v: FFTSettings(wall_transpose_bytes=v), "wall_transpose_bytes", "int"),
    ("fft-wall-samples", lambda v: FFTSettings(wall_solve_min_samples=v), "wall_solve_min_samples", "int"),
    ("set-fft-threads", lambda v: ps.set_fft_settings(threads=v), "threads", "int"),
    # inverse: optimizers, local solvers, physgrad, nets, operators, methods
    ("hig-lr", lambda v: _hig.HIG(_NET, lr=v), "lr", "pos"),
    ("hig-rcond", lambda v: _hig.HIG(_NET, rcond=v), "rcond", "float"),
    ("hig-exponent", lambda v: _hig.HIG(_NET, exponent=v), "exponent", "float"),
    ("hig-memory-budget", lambda v: _hig.HIG(_NET, memory_budget=v), "memory_budget", "int?"),
    ("hig-chunk-size", lambda v: _hig.HIG(_NET, chunk_size=v), "chunk_size", "int?"),
    ("gauss-newton-lr", lambda v: _hig.GaussNewton(_NET, lr=v), "lr", "pos"),
    ("gauss-newton-rcond", lambda v: _hig.GaussNewton(_NET, rcond=v), "rcond", "float"),
    ("jacobian-chunk-size", lambda v: _hig.per_sample_jacobian(_NET, torch.ones(2, 2), chunk_size=v),
     "chunk_size", "int?"),
    ("power-svd-rcond", lambda v: _hig.truncated_power_svd(torch.eye(2), torch.ones(2), rcond=v), "rcond", "float"),
    ("gradient-step-size", lambda v: _ls.GradientStepSolver(step_size=v), "step_size", "pos"),
    ("gradient-max-iter", lambda v: _ls.GradientStepSolver(max_iter=v), "max_iter", "int"),
    ("newton-max-iter", lambda v: _ls.NewtonSolver(max_iter=v), "max_iter", "int"),
    ("newton-step-size", lambda v: _ls.NewtonSolver(step_size=v), "step_size", "pos"),
    ("newton-clip", lambda v: _ls.NewtonSolver(clip=v), "clip", "pos?"),
    ("newton-rcond", lambda v: _ls.NewtonSolver(rcond=v), "rcond", "float"),
    ("inverse-gradient-max-iter", lambda v: _ls.InverseGradientSolver(max_iter=v), "max_iter", "int"),
    ("inverse-gradient-rcond", lambda v: _ls.InverseGradientSolver(rcond=v), "rcond", "float"),
    ("inverse-gradient-clip", lambda v: _ls.InverseGradientSolver(clip=v), "clip", "pos?"),
    ("lbfgsb-max-iter", lambda v: _ls.LBFGSBSolver(max_iter=v), "max_iter", "int"),
    ("lbfgsb-maxcor", lambda v: _ls.LBFGSBSolver(maxcor=v), "maxcor", "int"),
    ("lbfgsb-ftol", lambda v: _ls.LBFGSBSolver(ftol=v), "ftol", "pos"),
    ("lbfgsb-gtol", lambda v: _ls.LBFGSBSolver(gtol=v), "gtol", "pos"),
    ("lbfgsb-bounds", lambda v: _ls.LBFGSBSolver(bounds=(0.0, v)), "bounds", "pos?"),
    ("quadratic-damping", lambda v: _pg.QuadraticLoss(damping=v), "damping", "float"),
    ("quadratic-rcond", lambda v: _pg.QuadraticLoss(rcond=v), "rcond", "float"),
    ("fourier-ndim", lambda v: _pg.FourierTransform(v), "ndim", "int"),
    ("physgrad-loss-eta", lambda v: _pg.physical_gradient_loss(torch.ones(2, 2), torch.ones(2, 2), _ops.ScaleToy(),
                                                               eta=v), "eta", "pos"),
    ("physgrad-grad-scale", lambda v: _pg.physgrad(_ops.ScaleToy(), grad_scale=v), "grad_scale", "pos"),
    ("physgrad-eta", lambda v: _pg.physgrad(_ops.ScaleToy(), eta=v), "eta", "pos"),
    ("unet-levels", lambda v: _nets.UNet(levels=v), "levels", "int"),
    ("unet-filters", lambda v: _nets.UNet(filters=v), "filters", "int"),
    ("unet-in-channels", lambda v: _nets.UNet(in_channels=v), "in_channels", "int"),
    ("mlp-size", lambda v: _nets.MLP([1, v]), "sizes", "int"),
    ("grid-resolution", lambda v: ps.Grid((4, v)), "resolution", "int"),
    ("scale-toy-alpha", lambda v: _ops.ScaleToy(v), "alpha", "float"),
    ("heat-nu-t", lambda v: _ops.Heat(nu_t=v), "nu_t", "pos"),
    ("heat-threshold", lambda v: _ops.Heat(threshold=v), "threshold", "float"),
    ("heat-noise-floor", lambda v: _ops.Heat(noise_floor=v), "noise_floor", "float"),
    ("method-lr", lambda v: Method("m", "physics", lr=v), "lr", "pos"),
    ("method-momentum", lambda v: Method("m", "physics", momentum=v), "momentum", "float"),
    ("method-grad-clip", lambda v: Method("m", "physics", grad_clip=v), "grad_clip", "pos?"),
]

_BAD_VALUES = {  # every kind gets a string, a list and NaN; None unless it is allowed; ints also a float and 2**64
    "int": ["3", [3], NAN, None, 1.5, 2**64],
    "int?": ["3", [3], NAN, 1.5, 2**64],
    "seed": ["3", [3], NAN, 1.5, 2**64, -(2**63) - 1],
    "float": ["0.5", [0.5], NAN, None],
    "pos": ["0.5", [0.5], NAN, None, math.inf],
    "pos?": ["0.5", [0.5], NAN],
}
NUMBER_CASES = [(f"{name}-{bad!r}"[:60], call, arg, bad) for name, call, arg, kind in NUMBER_ARGS
                for bad in _BAD_VALUES[kind]]


@pytest.mark.parametrize("call, arg, bad", [c[1:] for c in NUMBER_CASES], ids=[c[0] for c in NUMBER_CASES])
def test_bad_number_gives_parameter_error_naming_the_argument(call, arg, bad):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(ParameterError) as info:
            call(bad)
    assert arg in str(info.value), str(info.value)


FLAG_AND_CHOICE_ARGS = [  # True/False or one of a few names expected: 1, 'yes', None or a list refused
    ("noise-normalize", lambda v: _noise.spectral_noise(G, normalize=v), "normalize"),
    ("vortex-staggered", lambda v: _noise.gaussian_vortex(G, (1.0, 1.0), 1.0, 1.0, staggered=v), "staggered"),
    ("vortex-wrap", lambda v: _noise.gaussian_vortex(G, (1.0, 1.0), 1.0, 1.0, wrap=v), "wrap"),
    ("solve-raise", lambda v: ps.Solve(raise_on_failure=v), "raise_on_failure"),
    ("solve-widen", lambda v: ps.Solve(widen_tolerance=v), "widen_tolerance"),
    ("hig-timing", lambda v: _hig.HIG(_NET, timing=v), "timing"),
    ("newton-saddle-free", lambda v: _ls.NewtonSolver(saddle_free=v), "saddle_free"),
    ("hig-reduction", lambda v: _hig.HIG(_NET, reduction=v), "reduction"),
    ("fft-engine", lambda v: FFTSettings(engine=v), "engine"),
    ("fft-planner", lambda v: FFTSettings(planner_effort=v), "planner_effort"),
    ("physgrad-reduction", lambda v: _pg.physical_gradient_loss(torch.ones(2, 2), torch.ones(2, 2), _ops.ScaleToy(),
                                                                reduction=v), "reduction"),
    ("unet-padding", lambda v: _nets.UNet(padding_mode=v), "padding_mode"),
    ("sine-closest", lambda v: _ops.Sine(1.0, closest=v), "closest"),
    ("poisson-convention", lambda v: _ops.Poisson(convention=v), "convention"),
]
FLAG_CASES = [(f"{name}-{bad!r}", call, arg, bad) for name, call, arg in FLAG_AND_CHOICE_ARGS
              for bad in (1, "yes", None, ["x"])]


@pytest.mark.parametrize("call, arg, bad", [c[1:] for c in FLAG_CASES], ids=[c[0] for c in FLAG_CASES])
def test_bad_flag_or_choice_gives_parameter_error_naming_the_argument(call, arg, bad):
    with pytest.raises(ParameterError) as info:
        call(bad)
    assert arg in str(info.value), str(info.value)


# ---- class 3: user callables that return the wrong shape, a flat tensor, a batch of 1 or NaN ------------
def flat_output(x, *args):
    return x.reshape(-1)


def first_sample_only(x, *args):
    return x[:1]


def nan_output(x, *args):
    return x * NAN


def drops_an_axis(x, *args):
    return x[..., :1]


def _solver_returning(fn):
    def bad_solver(forward, y_target, x0):
        return fn(x0)
    bad_solver.__name__ = fn.__name__
    return bad_solver


class ShapeChangingSolver(_ls.LocalSolver):
    def _solve(self, forward, y_target, x0):
        return x0[:1]


def _two_arg(fn):
    def wrapped(y_target, x0):
        return fn(x0)
    wrapped.__name__ = fn.__name__
    return wrapped


class _BadTransform:
    def __call__(self, y):
        return y[:1]

    def inverse(self, c):
        return c.real


CALLABLE_CASES = [  # (id, call, name of the callable in the message, error)
    *[(f"cg-preconditioner-{f.__name__}", lambda f=f: _cg(lambda x: 2 * x, torch.ones(3, 4), preconditioner=f),
       f.__name__, NonFiniteError if f is nan_output else ShapeError)
      for f in (flat_output, first_sample_only, nan_output, drops_an_axis)],
    *[(f"cg-projection-{f.__name__}", lambda f=f: _cg(lambda x: 2 * x, torch.ones(3, 4), project=f), f.__name__,
       NonFiniteError if f is nan_output else ShapeError) for f in (flat_output, first_sample_only, nan_output)],
    *[(f"cg-operator-{f.__name__}", lambda f=f: _cg(f, torch.ones(3, 4)), f.__name__, ShapeError)
      for f in (flat_output, first_sample_only)],
    *[(f"solver-operator-{f.__name__}", lambda f=f: _ls.SolverOperator(lambda x: x, _solver_returning(f))
       .local_inverse(torch.ones(3, 2), torch.ones(3, 2)), f.__name__,
       NonFiniteError if f is nan_output else ShapeError)
      for f in (flat_output, first_sample_only, nan_output, drops_an_axis)],
    *[(f"callable-operator-inverse-{f.__name__}", lambda f=f: CallableOperator(lambda x: x, _two_arg(f))
       .local_inverse(torch.ones(3, 2), torch.ones(3, 2)), f.__name__,
       NonFiniteError if f is nan_output else ShapeError)
      for f in (flat_output, first_sample_only, nan_output, drops_an_axis)],
    *[(f"callable-operator-physics-{f.__name__}", lambda f=f: CallableOperator(f).forward(torch.ones(3, 2)),
       f.__name__, ShapeError) for f in (flat_output, first_sample_only)],
    *[(f"local-solver-forward-{f.__name__}", lambda f=f: _ls.GradientStepSolver()(f, torch.ones(3, 2),
                                                                                  torch.ones(3, 2)),
       f.__name__, ShapeError) for f in (flat_output, first_sample_only)],
    ("local-solver-result", lambda: ShapeChangingSolver()(lambda x: x, torch.ones(3, 2), torch.ones(3, 2)),
     "ShapeChangingSolver", ShapeError),
    *[(f"hig-physics-{f.__name__}", lambda f=f: _hig.HIG(_NET, physics=f).step(torch.ones(3, 2), torch.ones(3, 2)),
       f.__name__, NonFiniteError if f is nan_output else ShapeError)
      for f in (flat_output, first_sample_only, nan_output)],
    ("hig-loss-fn", lambda: _hig.HIG(_NET).step(torch.ones(3, 2), torch.ones(3, 2), loss_fn=flat_output),
     "flat_output", ShapeError),
    ("quadratic-loss-transform", lambda: _pg.QuadraticLoss(transform=_BadTransform()).newton_step(
        torch.ones(3, 2), torch.zeros(3, 2)), "_BadTransform", ShapeError),
]


@pytest.mark.parametrize("call, fn_name, error", [c[1:] for c in CALLABLE_CASES], ids=[c[0] for c in CALLABLE_CASES])
def test_callable_returning_wrong_output_is_named(call, fn_name, error):
    with pytest.raises(error) as info:
        call()
    msg = str(info.value)
    assert fn_name in msg and "returned" in msg, msg
    if error is ShapeError:
        assert re.search(r"\(3,( ?[24])?\)|batch size 3", msg), msg  # the shape expected is named


# ---- class 4: NaN or infinite sample coordinates ------------------------------------------------------
_G1 = ps.Grid(8)
SAMPLE_CASES = [
    ("centered-2d", lambda p: _s(1).sample(torch.tensor([[p, 1.0]]))),
    ("centered-2d-per-sample", lambda p: _s(2).sample(torch.tensor([[[1.0, 1.0]], [[p, 1.0]]]), per_sample=True)),
    ("centered-vector", lambda p: ps.CenteredGrid.zeros(G, W, 1, channels=2).sample(torch.tensor([[1.0, p]]))),
    ("centered-1d", lambda p: ps.CenteredGrid.zeros(_G1, "wall", 1).sample(torch.tensor([[p]]))),
    ("centered-3d", lambda p: ps.CenteredGrid.zeros(G3, "periodic", 1).sample(torch.tensor([[p, 1.0, 1.0]]))),
    ("staggered-2d", lambda p: _v(1).sample(torch.tensor([[1.0, p]]))),
    ("staggered-periodic", lambda p: VP.sample(torch.tensor([[p, 1.0]]))),
    ("sample-padded-1d", lambda p: ps.sample_padded(torch.zeros(1, 1, 8), torch.tensor([[[p]]]))),
    ("sample-padded-2d", lambda p: ps.sample_padded(torch.zeros(1, 1, 8, 6), torch.tensor([[[p, 0.0]]]))),
]
SAMPLE_BAD = [(f"{name}-{p}", call, p) for name, call in SAMPLE_CASES for p in (NAN, math.inf, -math.inf)]


@pytest.mark.parametrize("call, point", [c[1:] for c in SAMPLE_BAD], ids=[c[0] for c in SAMPLE_BAD])
def test_non_finite_sample_coordinates_give_non_finite_error(call, point):
    with pytest.raises(NonFiniteError, match="NaN/Inf"):
        call(point)


# ---- class 5: empty batches (batch size 0) ---------------------------------------------------------------
# Choice: fields never hold an empty batch (refused where they are made), and padding, sampling and advection
# refuse one at their entry with a ShapeError; batched tensor functions without a field (cg, the local solvers
# and operators of inverse/) return the natural empty result.
EMPTY_CASES = [
    ("centered-grid", lambda: ps.CenteredGrid(torch.zeros(0, 8, 6), G, W)),
    ("centered-vector", lambda: ps.CenteredGrid(torch.zeros(0, 2, 8, 6), G, W)),
    ("staggered-grid", lambda: ps.StaggeredGrid((torch.zeros(0, 9, 6), torch.zeros(0, 8, 7)), G, W)),
    ("with-values", lambda: S.with_values(torch.zeros(0, 8, 6))),
    ("pad", lambda: ps.pad(torch.zeros(0, 8, 6), W.for_scalar(), G.dx)),
    ("pad-vector", lambda: ps.pad(torch.zeros(0, 2, 8, 6), W, G.dx, vector=True)),
    ("pad-staggered", lambda: ps.pad_staggered_component(torch.zeros(0, 9, 6), 0, W, G.dx)),
    ("sample-padded", lambda: ps.sample_padded(torch.zeros(0, 1, 8, 6), torch.zeros(0, 1, 2))),
    ("advect-trusted-field", lambda: ps.advect(ps.CenteredGrid._trusted(torch.zeros(0, 8, 6), G, S.boundary), V, 0.1)),
    ("uniform-velocity", lambda: _noise.uniform_velocity(G, torch.zeros(0, 2))),
    ("spectral-poisson", lambda: ps.spectral_poisson_solve(torch.zeros(0, 4, 4), 1.0, "dirichlet")),
    ("hig-step", lambda: _hig.HIG(_NET).step(torch.ones(0, 2), torch.ones(0, 2))),
]


@pytest.mark.parametrize("call", [c[1] for c in EMPTY_CASES], ids=[c[0] for c in EMPTY_CASES])
def test_empty_batch_gives_shape_error(call):
    with pytest.raises(ShapeError, match="empty"):
        call()


def test_empty_batch_natural_results_of_field_free_functions():
    assert _cg(lambda x: x, torch.ones(0, 4)).shape == (0, 4)
    assert _ops.ScaleToy().local_inverse(torch.ones(0, 2), torch.ones(0, 2)).shape == (0, 2)


def test_bad_class_inputs_write_nothing(tmp_path):
    """The classes above raise before anything is written: the working folder stays empty."""
    for call in [c[1] for c in BATCH_MISMATCH] + [c[1] for c in EMPTY_CASES]:
        with pytest.raises(PhisimError):
            call()
    assert list(tmp_path.iterdir()) == []


def test_non_finite_sample_points_give_nan_where_raising_would_cost_a_sync(monkeypatch):
    """On accelerators the finiteness check would force a device sync: the values sampled at NaN/Inf points are
    NaN there instead of a plausible clamped value (the accelerator branch, run on the CPU here)."""
    import phisim.field as field_module

    monkeypatch.setattr(field_module, "_finite_points", lambda index, name: torch.isfinite(index).all(-1))
    ones = ps.CenteredGrid(torch.ones(1, 8, 6), G, "periodic")
    out = ones.sample(torch.tensor([[NAN, 1.0], [2.0, 1.0]]))
    assert math.isnan(float(out[0, 0])) and float(out[0, 1]) == pytest.approx(1.0)
    out1 = ps.sample_padded(torch.ones(1, 1, 8), torch.tensor([[[math.inf], [3.0]]]))
    assert math.isnan(float(out1[0, 0, 0])) and float(out1[0, 0, 1]) == pytest.approx(1.0)
    out_v = ps.StaggeredGrid.zeros(G, P, 1).sample(torch.tensor([[1.0, -math.inf]]))
    assert bool(torch.isnan(out_v).all())



# ---- class: names the file layout reserves or cannot store ----------------------------------------------
BAD_NAMES = [".", "..", "", "a/b", "a\x00b", "line\nbreak"]


def _names_writer(tmp_path, **kw):
    from phisim.io import SimulationWriter

    return SimulationWriter(tmp_path / "names.h5", G, W, dataset_name="names", batch_size=1, **kw)


@pytest.mark.parametrize("name", BAD_NAMES + ["time"])
def test_field_names_that_cannot_be_stored(name, tmp_path):
    with pytest.raises(ParameterError, match="field name"):
        _names_writer(tmp_path, fields={name: "scalar"})
    assert not any(tmp_path.iterdir())  # nothing written


@pytest.mark.parametrize("name", BAD_NAMES + ["dataset_name", "grid_type", "n_spatial_dims", "n_trajectories",
                                              "simulation_parameters"])
def test_parameter_names_that_cannot_be_stored_or_are_reserved(name, tmp_path):
    with pytest.raises(ParameterError, match="parameter name"):
        _names_writer(tmp_path, fields={"u": "scalar"}, parameters={name: 1.0})
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("name", BAD_NAMES)
def test_constant_field_and_method_names_that_cannot_be_stored(name, tmp_path):
    from phisim.io import TrainingLog

    with pytest.raises(ParameterError, match="constant field name"):
        _names_writer(tmp_path, fields={"u": "scalar"}, constant_fields={name: torch.zeros(G.resolution)})
    with pytest.raises(ParameterError, match="method"):
        TrainingLog(tmp_path / "log.h5", name)
    assert not any(tmp_path.iterdir())


def test_fractional_frame_index_is_a_parameter_error(tmp_path):
    from phisim.io import read_simulation

    with _names_writer(tmp_path, fields={"u": "scalar"}) as w:
        w.append(0.0, u=torch.zeros(1, *G.resolution))
    data = read_simulation(tmp_path / "names.h5")
    with pytest.raises(ParameterError, match="frame index"):
        data.frame("u", 0.5)


def test_one_wording_for_missing_folder_and_pipe_files_in_library_and_commands(tmp_path):
    """phisim.checks.existing_file is the one check behind the readers and the command line."""
    assert cli_checks.existing_file is existing_file
    for fn in (lambda p: existing_file(p, "HDF5 file"), open_for_read):
        with pytest.raises(FileFormatError, match=r"HDF5 file .*nope\.h5 does not exist"):
            fn(tmp_path / "nope.h5")
        with pytest.raises(FileFormatError, match=r"HDF5 file .* is a folder, not a file"):
            fn(tmp_path)
