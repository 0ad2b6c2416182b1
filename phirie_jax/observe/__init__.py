"""Scene Observation: per-view masks → first-hit lifting onto the surface → voxel association.

``run_observe`` is the stage; the modules are its steps (``surface``, ``masks``, ``auto``,
``lift``, ``associate``) and ``evaluate`` scores instances against ground truth.
"""

from phirie_jax.observe.pipeline import run_observe

__all__ = ["run_observe"]
