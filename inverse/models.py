"""Trained models: the network and what rebuilds it, written beside the results file; inference from HDF5.

At the end of every run with an output file, :func:`inverse.train.train` writes ``<out>.<method>.model.pt``
(:func:`model_path`), a ``torch.save`` dictionary holding

* ``format`` (``'phisim-model/1'``), ``problem`` (name), ``factory`` and ``settings``: how to rebuild the
  network (``get_problem(factory, **settings).make_network()``; a factory ``module:function`` or
  ``/absolute/path/file.py:function`` for problems of your own, see :mod:`inverse.custom`), and
  ``factory_file``: the absolute path of the file that defines a factory of your own (empty for registered
  problems);
* ``network_class`` (``module.QualName``), ``parameters`` (count) and ``state_dict`` (the trained weights,
  BatchNorm running statistics included);
* ``input_shape`` (one sample's network input), ``dtype``, ``method``, ``seed``, ``iterations``.

:func:`load_model` returns the network in eval mode, ready for inference; :func:`predict_file` applies it to
an array of an HDF5 file (the command ``phisim predict``).
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from phisim.errors import FileFormatError, ParameterError, ShapeError

from .cli_checks import dataset_key, hdf5_file, model_file
from .custom import CustomProblem, is_factory_spec
from .problems import PROBLEMS, get_problem

__all__ = ["MODEL_FORMAT", "model_path", "problem_spec", "save_model", "read_model_file", "rebuild_problem",
           "load_model", "predict", "predict_file"]

#: Format tag of model files.
MODEL_FORMAT = "phisim-model/1"

_DTYPES = {"float32": torch.float32, "float64": torch.float64, "float16": torch.float16,
           "bfloat16": torch.bfloat16}


def model_path(out: str | os.PathLike, method: str) -> Path:
    """The model file of ``method`` beside the results file ``out``: ``<out>.<method>.model.pt``."""
    out = Path(out)
    return out.with_name(f"{out.name}.{method}.model.pt")


def _jsonable(v: Any) -> Any:
    if isinstance(v, tuple):
        v = list(v)
    if isinstance(v, list):
        return [_jsonable(x) for x in v] if all(_jsonable(x) is not _SKIP for x in v) else _SKIP
    if isinstance(v, (bool, int, float, str)) or v is None:
        return v
    return _SKIP


_SKIP = object()


def problem_spec(problem) -> dict:
    """How to rebuild ``problem``: ``{'factory': name or 'module:function', 'settings': {...}, 'source': ...}``.

    Problems made by :func:`inverse.problems.get_problem` or :func:`inverse.custom.load_problem` carry
    their spec (a factory file by its absolute path, ``source`` the file that defines the factory); for
    others it is derived from the class (registered name or ``module:Class``) and the dataclass fields that
    differ from their defaults and are plain values. A problem built with :func:`inverse.make_problem`
    directly has no factory (``None``): its model file needs ``load_model(path, network=...)``.
    """
    spec = getattr(problem, "spec", None)

    if isinstance(problem, CustomProblem) and not (isinstance(spec, dict) and spec.get("factory")):
        return {"factory": None, "settings": {}, "source": None}  # built in Python: not rebuildable by name
    if isinstance(spec, dict) and spec.get("factory"):
        settings = {k: _jsonable(v) for k, v in spec.get("settings", {}).items()}
        return {"factory": spec["factory"], "settings": {k: v for k, v in settings.items() if v is not _SKIP},
                "source": spec.get("source")}

    cls = type(problem)
    factory = next((n for n, c in PROBLEMS.items() if c is cls), None)
    if factory is None and getattr(problem, "name", None) in PROBLEMS and cls.__name__ == "FluidProblem":
        factory = problem.name
    if factory is None:
        factory = f"{cls.__module__}:{cls.__qualname__}"
    settings = {}
    if dataclasses.is_dataclass(problem):
        for f in dataclasses.fields(problem):
            if not f.init or f.name in ("methods", "newton_loss", "name", "spec"):
                continue
            value = getattr(problem, f.name)
            default = f.default if f.default is not dataclasses.MISSING else (
                f.default_factory() if f.default_factory is not dataclasses.MISSING else dataclasses.MISSING)
            if default is not dataclasses.MISSING and _jsonable(value) == _jsonable(default):
                continue
            j = _jsonable(value)
            if j is not _SKIP:
                settings[f.name] = j
    return {"factory": factory, "settings": settings, "source": None}


def save_model(path: str | os.PathLike, network: nn.Module, problem, *, method: str = "", seed: int = 0,
               iterations: int = 0, input_shape: tuple[int, ...] | None = None) -> Path:
    """Write a model file (atomically: a temporary file renamed into place).

    Args:
        path: The file (e.g. :func:`model_path`).
        network: The trained network (unwrapped, not the DDP wrapper).
        problem: The problem it was trained on (its :func:`problem_spec` is stored).
        method: Training method name.
        seed: Training seed.
        iterations: Iterations trained.
        input_shape: Shape of one sample's network input.

    Returns:
        The path.
    """
    spec = problem_spec(problem)
    dtype = next((p.dtype for p in network.parameters()), torch.float32)
    state = {
        "format": MODEL_FORMAT,
        "problem": str(getattr(problem, "name", "")),
        "factory": spec["factory"] or "",
        "factory_file": spec.get("source") or "",
        "settings_json": json.dumps(spec["settings"]),
        "network_class": f"{type(network).__module__}.{type(network).__qualname__}",
        "parameters": int(sum(p.numel() for p in network.parameters())),
        "state_dict": {k: v.detach().cpu() for k, v in network.state_dict().items()},
        "input_shape": list(input_shape) if input_shape is not None else None,
        "dtype": str(dtype).replace("torch.", ""),
        "method": str(method),
        "seed": int(seed),
        "iterations": int(iterations),
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)
    return path


def read_model_file(path: str | os.PathLike) -> dict:
    """The content of a model file (weights on the CPU), validated.

    Raises:
        FileFormatError: Missing, unreadable or not a phisim model file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"model file {path} does not exist")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - anything unreadable is a format problem
        first = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else ""
        raise FileFormatError(f"{path} is not a readable model file ({type(exc).__name__}: {first})") from exc
    if not isinstance(state, dict) or state.get("format") != MODEL_FORMAT:
        raise FileFormatError(f"{path} is not a phisim model file (format {MODEL_FORMAT!r} expected)")
    for key in ("factory", "settings_json", "state_dict", "network_class"):
        if key not in state:
            raise FileFormatError(f"model file {path} lacks {key!r}")
    state["settings"] = json.loads(state["settings_json"])
    return state


def _factory_candidates(factory: str, factory_file: str, model_file: Path) -> list[str]:
    """Factory names to try, best first: as stored, then the defining file, then a relative file anchored.

    A ``file.py:function`` stored relative (model files of earlier versions) is looked up in the working
    directory and then beside the model file and in each folder above it (a model written to ``out/`` under
    the folder the training ran in finds ``examples/...`` there).
    """
    if not is_factory_spec(factory):
        return [factory]
    module, _, func = factory.rpartition(":")
    out = [factory]
    if factory_file:
        out.append(f"{factory_file}:{func}")
    is_file = module.endswith(".py") or "/" in module or "\\" in module
    if is_file and not Path(module).expanduser().is_absolute():
        out += [f"{folder / module}:{func}" for folder in Path(model_file).resolve().parents]
    return list(dict.fromkeys(out))


def rebuild_problem(state: dict, path: str | os.PathLike, settings: dict | None = None):
    """The problem a model file was trained on, rebuilt from its stored factory and settings.

    The factory resolves from any working directory: registered names and importable ``module:function``
    as they are; a factory file by its absolute path (as stored since factory files are resolved at
    training time), else by the module's own file (``factory_file``), else (older files with a relative
    path) relative to the working directory or to the model file's folder and the folders above it.

    Args:
        state: The model file's content (:func:`read_model_file`).
        path: The model file (for messages and anchored look-ups).
        settings: The factory's settings (default: the stored ones).

    Returns:
        The problem.

    Raises:
        ParameterError: No candidate resolves (the message names the stored factory and ``network=``).
    """
    if settings is None:
        settings = {k: tuple(v) if isinstance(v, list) else v for k, v in state["settings"].items()}
    candidates = _factory_candidates(state["factory"], state.get("factory_file", ""), Path(path))
    first_error = None
    for name in candidates:
        try:
            return get_problem(name, **settings)
        except ParameterError as exc:
            missing = "does not exist" in str(exc) or "cannot import" in str(exc)
            if not missing or len(candidates) == 1:
                raise
            first_error = first_error or exc
    raise ParameterError(f"model file {path}: its problem factory {state['factory']!r} cannot be found from "
                         f"{Path.cwd()} ({first_error}); run from a folder where it resolves, or pass the network: "
                         "load_model(path, network=...)") from first_error


def load_model(path: str | os.PathLike, *, network: nn.Module | None = None, device: str | torch.device = "cpu"
               ) -> nn.Module:
    """Rebuild a trained network from its model file, in eval mode on ``device``.

    Args:
        path: A model file written by training (:func:`model_path`).
        network: A network to load the weights into instead of rebuilding it from the stored problem factory.
        device: Torch device.

    Returns:
        The network (``eval()`` mode; gradients still enabled, wrap calls in ``torch.no_grad()``).
        ``net.phisim_model`` holds the file's metadata (problem, method, input shape, ...).

    Raises:
        FileFormatError: Not a model file, or weights that do not fit the network (a file from a different
            network).
        ParameterError: The problem factory cannot be rebuilt (e.g. its module is not importable).
    """
    state = read_model_file(path)
    if network is None:
        if not state["factory"]:
            raise ParameterError(f"model file {path} comes from a problem built in Python (make_problem without "
                                 "a factory); pass the network to load the weights into: load_model(path, "
                                 "network=problem.make_network()), or train a problem made by its factory "
                                 "(get_problem('file.py:function') or 'module:function') to store it")
        settings = {k: tuple(v) if isinstance(v, list) else v for k, v in state["settings"].items()}
        network = rebuild_problem(state, path, settings).make_network()
    expected = state["network_class"].rsplit(".", 1)[-1]
    if type(network).__qualname__.rsplit(".", 1)[-1] != expected:
        raise FileFormatError(f"model file {path} holds a {expected}, not a {type(network).__name__}")
    dtype = _DTYPES.get(state.get("dtype"), torch.float32)
    network = network.to(dtype=dtype)
    try:
        network.load_state_dict(state["state_dict"], strict=True)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        raise FileFormatError(f"model file {path} is from a different network: "
                              f"{' '.join(s.strip() for s in first[:3])[:300]}") from exc
    network = network.to(device=torch.device(device)).eval()
    network.phisim_model = {k: v for k, v in state.items() if k not in ("state_dict", "settings_json")}
    return network


def predict(network: nn.Module, inputs: np.ndarray | torch.Tensor, *, batch_size: int = 64) -> np.ndarray:
    """Apply a network in eval mode to ``inputs`` ``(N, *input_shape)`` batch by batch (no gradients).

    Returns:
        The outputs ``(N, *output_shape)`` as a numpy array.
    """
    if batch_size < 1:
        raise ParameterError(f"batch_size must be >= 1, got {batch_size}")
    p = next(network.parameters())
    x = torch.as_tensor(np.asarray(inputs))
    outs = []
    network.eval()
    with torch.no_grad():
        for i in range(0, x.shape[0], batch_size):
            outs.append(network(x[i:i + batch_size].to(device=p.device, dtype=p.dtype)).cpu())
    return torch.cat(outs).numpy() if outs else np.zeros((0,))


def _inputs_from(arr: np.ndarray, key: str, input_shape: list[int] | None, path: Path) -> tuple[np.ndarray, tuple]:
    """Reshape an array of the input file to ``(N, *input_shape)``; returns it and the leading shape."""
    if key.startswith("t1_fields/") and arr.ndim >= 3:  # Well vectors (B, T, *res, d) -> (B, T, d, *res)
        arr = np.moveaxis(arr, -1, 2)
    if input_shape is None:
        return arr, arr.shape[:1]
    shape = tuple(input_shape)
    n = len(shape)
    if tuple(arr.shape[-n:]) == shape:
        lead = arr.shape[:-n]
    elif shape[0] == 1 and tuple(arr.shape[-(n - 1):] if n > 1 else ()) == shape[1:]:
        lead = arr.shape[:arr.ndim - (n - 1)]  # a channel axis of 1 is added
    else:
        raise ShapeError(f"{path}:/{key} has shape {arr.shape}; the network takes inputs of shape {shape} "
                         "(optionally after leading batch/time axes)")
    return arr.reshape((-1, *shape)), lead


def predict_file(model: str | os.PathLike, inputs: str | os.PathLike, out: str | os.PathLike, *,
                 key: str | None = None, device: str = "cpu", batch_size: int = 64) -> Path:
    """Apply a trained model to an array of an HDF5 file and write the predictions to a new HDF5 file.

    The array ``key`` (default: the only dataset of the file, else ``inputs``) is reshaped to
    ``(N, *input_shape)``: leading axes (e.g. trajectories and time of a Well field ``t0_fields/<name>``
    ``(B, T, *res)``) are flattened and restored in the output, a channel axis of 1 is added when the
    network takes one channel. The output file holds ``/predictions`` (leading axes, then the network's output
    shape), attributes ``model``, ``input_file``, ``input_key``, ``problem`` and ``method``. The predictions are
    the network's raw output (a problem's own post-processing, e.g. the heat problem's mean correction in
    :meth:`~inverse.problems.HeatProblem.predict`, is not applied).

    Returns:
        The output path.

    Raises:
        FileFormatError: Unreadable input file, missing key, or a bad model file.
        ShapeError: The array does not fit the network's input shape.
    """
    import h5py

    order = "predict_file(model, inputs, out)"
    model_file(model, argument_order=order)  # the same checks and wording as `phisim predict`
    inputs = hdf5_file(inputs, "input file", argument_order=order)
    key = dataset_key(inputs, key, flag="key=")
    net = load_model(model, device=device)
    meta = net.phisim_model
    with h5py.File(inputs, "r") as f:
        arr = np.asarray(f[key])
    x, lead = _inputs_from(arr, key, meta.get("input_shape"), inputs)
    y = predict(net, x, batch_size=batch_size)
    y = y.reshape((*lead, *y.shape[1:]))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(out, "w") as g:
        g.create_dataset("predictions", data=y, compression="gzip")
        g.attrs.update({"model": str(model), "input_file": str(inputs), "input_key": key,
                        "problem": meta.get("problem", ""), "method": meta.get("method", "")})
    return out
