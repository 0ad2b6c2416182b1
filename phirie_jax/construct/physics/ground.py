"""The ground plane every physics model stands on, and the drop test's simulation options.

One home for what ``scene.xml`` (``supports.fit_background``'s floor), the drop-test models
(``droptest.build_model``) and MuJoCo Warp's bank model (``warp_batch.bank_model``) share, so the
drop test's two builders cannot drift apart.
"""

from __future__ import annotations

import mujoco

from phirie_jax.construct.physics.config import DropTestConfig

PLANE_HALF_SIZE = 5.0     # m; the plane is infinite for collisions, this is only its drawn half extent
PLANE_GRID = 0.05         # m; spacing of the grid lines a viewer draws on it
PLANE_SIZE = (PLANE_HALF_SIZE, PLANE_HALF_SIZE, PLANE_GRID)   # MuJoCo's plane ``size``


def add_drop_plane(spec: mujoco.MjSpec) -> None:
    """The drop test's ground: a plane through the origin, normal +z, named "plane". The body's priors
    govern its contact with the plane: MuJoCo takes the larger friction of a pair (the plane has
    none) and mixes solref/solimp by solmix (the plane's is 0)."""
    spec.worldbody.add_geom(name="plane", type=mujoco.mjtGeom.mjGEOM_PLANE, size=list(PLANE_SIZE),
                            friction=[0.0, 0.0, 0.0], solmix=0.0)


def set_drop_options(opt, config: DropTestConfig) -> None:
    """The drop test's step and solver settings on a spec's ``option``."""
    opt.timestep = config.timestep
    opt.iterations = config.solver_iterations
    opt.ls_iterations = config.line_search_iterations
    opt.tolerance = config.tolerance
    opt.solver = mujoco.mjtSolver.mjSOL_CG if config.solver == "cg" else mujoco.mjtSolver.mjSOL_NEWTON
    opt.jacobian = mujoco.mjtJacobian.mjJAC_SPARSE if config.jacobian == "sparse" else mujoco.mjtJacobian.mjJAC_DENSE
