"""Incompressible flow on MAC grids: bodies, pressure projection, viscosity, forces, time steps.

Modules:

* :mod:`~phisim.fluid.geometry` -- body shapes as signed distance functions (box, sphere, rotated box,
  union, your own function);
* :mod:`~phisim.fluid.bodies` -- :class:`Obstacle` (resting staircase cells) and :class:`Body` (a geometry
  with a prescribed motion, no-slip or free-slip, rasterised to fractional face weights);
* :mod:`~phisim.fluid.projection` -- :class:`Projection` (built once per domain) and :func:`make_incompressible`
  with walls, inflows, outflows, periodic sides and bodies;
* :mod:`~phisim.fluid.viscosity` -- :func:`diffuse_velocity`;
* :mod:`~phisim.fluid.forces` -- drag and lift on bodies, pressure at probe points;
* :mod:`~phisim.fluid.control_volume` -- the force on what lies in a box, from the momentum balance over the box;
* :mod:`~phisim.fluid.step` -- the parts of a split step (buoyancy, energy, CFL, the wall values of sharp bodies
  with the anticipated pressure gradient: :func:`anticipate_pressure`) and :class:`FluidState`;
* :mod:`~phisim.fluid.stepper` -- :class:`FluidStepper` (settings checked and operators built once; the way to
  step a flow), and the same steps as pure functions, :func:`step` and :func:`navier_stokes_step`;
* :mod:`~phisim.fluid.transport` -- :class:`AdvectionDiffusionStepper` (a scalar in a given flow) and
  :class:`BurgersStepper`;
* :mod:`~phisim.fluid.integrators` -- second-/third-order time integrators (:func:`navier_stokes_rk_step`:
  ``'rk2'``, ``'rk3'``, ``'imex2'``; the table of every integrator, ``'split2'`` included) and the MAC
  :func:`convection` term.
"""

from phisim.fluid.bodies import Body, Obstacle, SolidLayout, obstacle_mask, open_face_masks, solid_layout
from phisim.fluid.control_volume import ControlVolumeForces, control_volume_box, control_volume_force
from phisim.fluid.forces import BodyForces, body_forces, probe_pressure, wall_pressure
from phisim.fluid.geometry import SDF, Box, Geometry, RotatedBox, Sphere, Union, fluid_fraction
from phisim.fluid.integrators import INTEGRATORS, convection, navier_stokes_rk_step
from phisim.fluid.projection import (
    PRESSURE_SOLVE,
    Projection,
    ProjectionResult,
    impose_solids,
    make_incompressible,
    net_boundary_flux,
    relative_divergence,
    solid_flux,
)
from phisim.fluid.step import FluidState, anticipate_pressure, buoyancy, cfl_dt, kinetic_energy, normalize_energy
from phisim.fluid.stepper import FluidStepper, navier_stokes_step, step
from phisim.fluid.transport import AdvectionDiffusionStepper, BurgersStepper
from phisim.fluid.viscosity import VISCOSITY_SCHEMES, diffuse_velocity

__all__ = [
    "Geometry", "Box", "Sphere", "RotatedBox", "Union", "SDF", "fluid_fraction",
    "Obstacle", "Body", "SolidLayout", "solid_layout", "obstacle_mask", "open_face_masks",
    "Projection", "ProjectionResult", "make_incompressible", "relative_divergence", "impose_solids",
    "net_boundary_flux", "solid_flux", "PRESSURE_SOLVE",
    "diffuse_velocity", "VISCOSITY_SCHEMES", "anticipate_pressure",
    "INTEGRATORS", "convection", "navier_stokes_rk_step",
    "BodyForces", "body_forces", "probe_pressure", "wall_pressure",
    "ControlVolumeForces", "control_volume_force", "control_volume_box",
    "buoyancy", "kinetic_energy", "normalize_energy", "cfl_dt", "navier_stokes_step", "FluidState", "step",
    "FluidStepper", "AdvectionDiffusionStepper", "BurgersStepper",
]
