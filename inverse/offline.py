"""Offline training: stream samples from a dataset folder in The Well's layout instead of simulating them.

:class:`DatasetSampler` is a ``data`` function for :func:`inverse.custom.make_problem`: it draws random
trajectories of a split (``<dataset>/data/<split>/*.h5``, e.g. written by ``phisim simulate`` or a public
Well dataset) with the trainer's generator and returns two frames of one field, ``x_true`` (frame
``x_frame``) and ``y_target`` (frame ``y_frame``). With a physics function matching the dataset every method
trains offline; without one, :func:`dataset_problem` (registered as the problem ``well``) trains the
network ``y -> x`` supervised.

Example (the earlier state of a heat dataset from its last frame)::

    phisim simulate heat --trajectories 64 --out data/heat
    phisim train well supervised --setting data_dir=data/heat --setting field=temperature --out out/well.h5
"""

from __future__ import annotations

import os
import warnings

import h5py
import numpy as np
import torch
from torch import nn

from phisim.errors import FileFormatError, ParameterError

from .nets import MLP, UNet
from .problem import Method

__all__ = ["DatasetSampler", "FieldNet", "dataset_problem"]


class DatasetSampler:
    """Random frame pairs of one field from a Well-layout dataset split.

    Args:
        data_dir: The dataset folder (``data/<split>/*.h5`` inside).
        field: Field name (a ``t0_fields`` scalar or a ``t1_fields`` vector).
        split: ``'train'``, ``'valid'`` or ``'test'``.
        x_frame: Frame index of ``x_true`` (negative counts from the end).
        y_frame: Frame index of ``y_target``.

    Attributes:
        files: The split's files.
        shape: Shape of one sample ``(*res)`` for a scalar, ``(d, *res)`` for a vector field.
        trajectories: Number of trajectories in the split.

    Raises:
        FileFormatError: The folder is not a Well-layout dataset, or the field is missing from a file.
        ParameterError: A frame index out of range.
    """

    def __init__(self, data_dir: str | os.PathLike, field: str, split: str = "train", x_frame: int = 0,
                 y_frame: int = -1):
        from phisim.simulate import check_dataset_dir

        self.files = check_dataset_dir(data_dir, split)
        self.field = field
        self._index: list[tuple[int, int]] = []
        self._handles: dict[int, h5py.File] = {}
        shapes = set()
        for i, p in enumerate(self.files):
            with h5py.File(p, "r") as f:
                group = next((g for g in ("t0_fields", "t1_fields") if g in f and field in f[g]), None)
                if group is None:
                    names = [n for g in ("t0_fields", "t1_fields") if g in f for n in f[g]]
                    raise FileFormatError(f"{p} has no field {field!r}; fields: {names}")
                ds = f[group][field]
                if not ds.attrs.get("time_varying", True):
                    raise FileFormatError(f"{p}: field {field!r} is constant in time; pick a time-varying field")
                if i == 0:
                    self.vector = group == "t1_fields"
                    self.n_frames = ds.shape[1]
                shapes.add(ds.shape[2:])
                self.n_frames = min(self.n_frames, ds.shape[1])
                self._index += [(i, b) for b in range(ds.shape[0])]
        if len(shapes) != 1:
            raise FileFormatError(f"the files of {data_dir}/data/{split} have different grids {sorted(shapes)}")
        res = shapes.pop()
        self.shape = (res[-1], *res[:-1]) if self.vector else tuple(res)
        self.frames = []
        for name, k in (("x_frame", x_frame), ("y_frame", y_frame)):
            k = int(k)
            kk = k + self.n_frames if k < 0 else k
            if not 0 <= kk < self.n_frames:
                raise ParameterError(f"{name}={k} out of range: the files have {self.n_frames} frames")
            self.frames.append(kk)
        self.trajectories = len(self._index)

    def _read(self, file: int, traj: int, frame: int) -> np.ndarray:
        f = self._handles.get(file)
        if f is None:
            f = self._handles[file] = h5py.File(self.files[file], "r")
        a = np.asarray(f["t1_fields" if self.vector else "t0_fields"][self.field][traj, frame])
        return np.moveaxis(a, -1, 0) if self.vector else a

    def __call__(self, batch_size: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """``(x_true, y_target)`` of ``batch_size`` trajectories drawn (with replacement) by ``generator``."""
        pick = torch.randint(self.trajectories, (batch_size,), generator=generator).tolist()
        xs, ys = [], []
        for k in pick:
            file, traj = self._index[k]
            xs.append(self._read(file, traj, self.frames[0]))
            ys.append(self._read(file, traj, self.frames[1]))
        return torch.from_numpy(np.stack(xs)), torch.from_numpy(np.stack(ys))

    def all(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(x_true, y_target)`` of every trajectory of the split, in file order."""
        xs = [self._read(f, t, self.frames[0]) for f, t in self._index]
        ys = [self._read(f, t, self.frames[1]) for f, t in self._index]
        return torch.from_numpy(np.stack(xs)), torch.from_numpy(np.stack(ys))

    def close(self) -> None:
        """Close the open files."""
        for f in self._handles.values():
            f.close()
        self._handles.clear()


class FieldNet(nn.Module):
    """A network ``field -> field`` for one sample shape: a U-net in 2-D, an MLP over the cells otherwise.

    Scalar fields ``(B, *res)`` get a channel axis for the U-net and lose it again; vector fields
    ``(B, d, *res)`` use ``d`` channels.

    Args:
        shape: One sample's shape (``(*res)`` or ``(d, *res)``).
        vector: Whether the first axis of ``shape`` is a channel axis.
        levels: U-net levels (2-D).
        filters: U-net filters (2-D).
        hidden: MLP width (other dimensions).
    """

    def __init__(self, shape, vector: bool, levels: int = 3, filters: int = 16, hidden: int = 128):
        super().__init__()
        self.shape, self.vector = tuple(int(s) for s in shape), bool(vector)
        res = self.shape[1:] if vector else self.shape
        channels = self.shape[0] if vector else 1
        if len(res) == 2:
            self.net = UNet(channels, channels, levels=levels, filters=filters, padding_mode="replicate")
        else:
            n = int(np.prod(self.shape))
            self.net = MLP([n, hidden, hidden, n], activation="relu")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` ``(B, *shape)`` to a field of the same shape."""
        if isinstance(self.net, UNet):
            return self.net(x)[:, :] if self.vector else self.net(x[:, None])[:, 0]
        return self.net(x.reshape(x.shape[0], -1)).reshape(x.shape)


def dataset_problem(data_dir: str, field: str, split: str = "train", x_frame: int = 0, y_frame: int = -1,
                    batch_size: int = 16, lr: float = 1e-3, levels: int = 3, filters: int = 16):
    """The problem ``well``: learn frame ``x_frame`` of a field from frame ``y_frame``, supervised, offline.

    Args:
        data_dir: Dataset folder in The Well's layout.
        field: Field name.
        split: Split to train on.
        x_frame: Frame the network predicts.
        y_frame: Frame the network sees.
        batch_size: Samples per batch.
        lr: Adam learning rate.
        levels: U-net levels (2-D data).
        filters: U-net filters (2-D data).

    Returns:
        A :class:`~inverse.custom.CustomProblem` whose only method is ``supervised`` (no physics: the y-space
        loss is logged as NaN). Its held-out set is every trajectory of the ``valid`` split (else ``test``;
        ``problem.heldout_split`` says which, None when neither has files and held-out samples are drawn
        from the training split, with a warning); ``problem.heldout_source`` says it in words (training
        summaries and logs report it).

    Raises:
        FileFormatError: Bad dataset folder or field.
    """
    from .custom import make_problem

    sampler = DatasetSampler(data_dir, field, split, x_frame, y_frame)

    def no_physics(x):
        raise ParameterError("the dataset problem has no physics; train it with the method 'supervised' or "
                             "build a problem with make_problem(data=DatasetSampler(...), physics=...)")

    p = make_problem("well", data=sampler, physics=no_physics, batch_size=batch_size, lr=lr,
                     network=lambda: FieldNet(sampler.shape, sampler.vector, levels, filters))
    p.methods = {"supervised": Method("supervised", "supervised", lr=lr)}
    p.sampler = sampler
    p.has_physics = False
    p.loss_name = "none (offline data without physics)"
    p.heldout_split = None
    for other in ("valid", "test"):
        if other == split:
            continue
        try:
            held = DatasetSampler(data_dir, field, other, x_frame, y_frame)
        except FileFormatError:
            continue
        _heldout_from_split(p, held)
        p.heldout_split = other
        p.heldout_source = (f"{held.trajectories} held-out samples: all trajectories of the {other!r} split of "
                            f"{data_dir}")
        break
    if p.heldout_split is None:
        p.heldout_source = (f"{p.heldout_size} held-out samples drawn from the {split!r} split, the data training "
                            f"draws from: {data_dir} has no valid or test files")
        warnings.warn(f"{data_dir} has no files in data/valid or data/test: the held-out evaluation draws "
                      f"{p.heldout_size} samples from the {split!r} split the network trains on, so it does not "
                      "measure generalisation; simulate more files (more --trajectories or fewer "
                      "--trajectories-per-file) to get valid/test files", UserWarning, stacklevel=2)
    return p


def _heldout_from_split(problem, held: DatasetSampler) -> None:
    """Make ``problem.heldout()`` every trajectory of another split (instead of draws from the training data)."""
    problem.heldout_size = held.trajectories
    sample, cache = problem.sample, {}

    def heldout(device=None):
        key = str(torch.device(device) if device is not None else "cpu")
        if key not in cache:
            data = problem.data
            problem.data = lambda batch_size, generator: held.all()
            try:
                cache[key] = sample(held.trajectories, torch.Generator(), device=device)
            finally:
                problem.data = data
        return cache[key]

    problem.heldout = heldout
