"""Translation between phisim boundaries and The Well's ``boundary_conditions`` (used by :mod:`phisim.io`).

:func:`well_bc_type` gives the Well type of a condition; :func:`condition_to_json` / :func:`condition_from_json`
store the exact conditions in ``/extras`` (and the journal header); :func:`boundary_from_well` rebuilds a
boundary from the Well groups of a foreign file.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import torch

from phisim.boundary import (
    Boundary,
    BoundaryCondition,
    Dirichlet,
    FreeSlipWall,
    Inflow,
    Neumann,
    NoSlipWall,
    Open,
    Periodic,
)
from phisim.errors import FileFormatError, ParameterError
from phisim.grid import Grid
from phisim.io.h5util import attr_str, attr_str_list, need, need_attr

__all__ = ["well_bc_type", "condition_to_json", "condition_from_json", "boundary_from_well"]

# ---- boundary <-> Well bc_type ------------------------------------------------------------------------


def well_bc_type(condition: BoundaryCondition) -> str:
    """The Well's ``bc_type`` of one phisim boundary condition.

    Args:
        condition: A phisim condition on one side of one axis.

    Returns:
        ``'PERIODIC'`` for :class:`Periodic`, ``'OPEN'`` for :class:`Open`, and ``'WALL'`` for
        :class:`NoSlipWall`, :class:`FreeSlipWall`, :class:`Dirichlet` and :class:`Neumann` (a closed side
        with a prescribed value or flux).

    Raises:
        ParameterError: For a condition type this module does not know.
    """
    if isinstance(condition, Periodic):
        return "PERIODIC"
    if isinstance(condition, (Open, Inflow)):
        return "OPEN"
    if isinstance(condition, (NoSlipWall, FreeSlipWall, Dirichlet, Neumann)):
        return "WALL"
    raise ParameterError(f"no Well boundary type is known for condition {condition!r}")


def condition_to_json(c: BoundaryCondition) -> dict:
    """A JSON-serialisable description of one condition (read back by :func:`condition_from_json`).

    Raises:
        ParameterError: For a condition type that cannot be stored.
    """
    if isinstance(c, Inflow):  # a function itself is not stored: its name is, and the side reads back as open
        if c.varying:
            return {"type": "inflow", "function": getattr(c.velocity, "__qualname__", repr(c.velocity))}
        return {"type": "inflow", "velocity": _value_to_json(c.velocity)}
    if isinstance(c, Periodic):
        return {"type": "periodic"}
    if isinstance(c, Open):
        return {"type": "open"}
    if isinstance(c, FreeSlipWall):
        return {"type": "free_slip"}
    if isinstance(c, NoSlipWall):
        v = None if c.velocity is None else [float(x) for x in c.velocity]
        return {"type": "no_slip", "velocity": v}
    if isinstance(c, Dirichlet):
        return {"type": "dirichlet", "value": _value_to_json(c.value)}
    if isinstance(c, Neumann):
        return {"type": "neumann", "flux": _value_to_json(c.flux)}
    raise ParameterError(f"cannot store boundary condition {c!r}")


def _value_to_json(v):
    if isinstance(v, torch.Tensor):
        return {"tensor": v.detach().cpu().tolist()}
    if isinstance(v, np.ndarray):
        return {"tensor": v.tolist()}
    if isinstance(v, (tuple, list)):
        return [float(x) for x in v]
    return float(v)


def _value_from_json(v):
    if isinstance(v, dict):
        return torch.tensor(v["tensor"])
    if isinstance(v, list):
        return tuple(float(x) for x in v)
    return float(v)


def condition_from_json(d: dict) -> BoundaryCondition:
    """The condition described by ``d`` (see :func:`condition_to_json`); an inflow given by a function reads
    back as :class:`Open`.

    Raises:
        FileFormatError: For an unknown description.
    """
    kind = d.get("type")
    if kind == "periodic":
        return Periodic()
    if kind == "open":
        return Open()
    if kind == "inflow":
        return Inflow(_value_from_json(d["velocity"])) if "velocity" in d else Open()
    if kind == "free_slip":
        return FreeSlipWall()
    if kind == "no_slip":
        v = d.get("velocity")
        return NoSlipWall(None if v is None else tuple(float(x) for x in v))
    if kind == "dirichlet":
        return Dirichlet(_value_from_json(d["value"]))
    if kind == "neumann":
        return Neumann(_value_from_json(d["flux"]))
    raise FileFormatError(f"unknown boundary condition {d!r} in /extras/boundary")


_FROM_WELL = {"PERIODIC": Periodic, "WALL": NoSlipWall, "OPEN": Open}


def boundary_from_well(f: h5py.File, grid: Grid, spatial: list[str], p: Path) -> Boundary:
    """The boundary of a foreign Well file from its ``/boundary_conditions`` groups (PERIODIC -> Periodic,
    WALL -> NoSlipWall, OPEN -> Open; sides without a group are open).

    Raises:
        FileFormatError: Missing or malformed groups, or inconsistent periodic sides.
    """
    sides: list[list[BoundaryCondition]] = [[Open(), Open()] for _ in range(grid.rank)]
    bcs = f.get("boundary_conditions")
    if not isinstance(bcs, h5py.Group):
        raise FileFormatError(f"{p}: missing group /boundary_conditions")
    for key in bcs:
        grp = bcs[key]
        bc_type = attr_str(need_attr(grp, "bc_type", p)).upper()
        if bc_type not in _FROM_WELL:
            raise FileFormatError(f"{p}: {grp.name} has unknown bc_type {bc_type!r} (PERIODIC, WALL, OPEN)")
        assoc = attr_str_list(need_attr(grp, "associated_dims", p))
        mask = np.asarray(need(grp, "mask", p, h5py.Dataset)[()], dtype=bool)
        if len(assoc) != 1 or assoc[0] not in spatial or mask.ndim != 1:
            continue  # boundaries not aligned with one axis do not map onto a phisim Boundary
        a = spatial.index(assoc[0])
        for side, idx in ((0, 0), (1, -1)):
            if mask.size and mask[idx]:
                sides[a][side] = _FROM_WELL[bc_type]()
    try:
        return Boundary(tuple((lo, hi) for lo, hi in sides))
    except Exception as exc:  # inconsistent periodic sides
        raise FileFormatError(f"{p}: inconsistent boundary_conditions: {exc}") from exc
