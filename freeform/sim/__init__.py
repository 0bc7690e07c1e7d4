"""Voxelyze's soft-voxel physics in Taichi (see docs/physics.md).

Public surface: ``Simulator(config).simulate(grids) -> SimResult``, ``SimConfig``, ``Material``.
``Engine`` and ``Layout`` are the documented lower level (fixed voxels, initial velocities, per-step traces).
Importing this package does not initialise Taichi; the first ``Simulator`` run does.
"""

from freeform.sim.config import Material, SimConfig
from freeform.sim.engine import Engine, recommended_dt
from freeform.sim.layout import Layout, build_layout
from freeform.sim.simulator import Recording, SimResult, Simulator, Trace
from freeform.sim.terrain import Terrain

__all__ = ["Engine", "Layout", "Material", "Recording", "SimConfig", "SimResult", "Simulator", "Terrain", "Trace",
           "build_layout", "recommended_dt"]
