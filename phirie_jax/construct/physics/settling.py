"""The object stage's settling check, supplied by physics.

Object construction ranks candidates by, among others, how far each settles when dropped at
its placement (the paper's settling check). The object stage does not import the simulator:
the pipeline hands it a ``CandidateSettler`` made here, so physics depends on objects' outputs
and never the other way round.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from phirie_jax.construct.physics.config import PhysicsConfig

STAND_IN = "convex hull stand-in"

# (meshes: [(vertices (V, 3), faces (F, 3))], poses: [(4, 4) Sim(3)], up (3,), category) → check rows
CandidateSettler = Callable[[Sequence[tuple[np.ndarray, np.ndarray]], Sequence[np.ndarray], np.ndarray, "str | None"],
                            list[dict]]


def candidate_settler(config: PhysicsConfig = PhysicsConfig()) -> CandidateSettler:
    """Drop-tests candidate placements in one batch (single-hull stand-in) → their settling rows."""
    from phirie_jax.construct.physics.droptest import drop_test_meshes, settling_check

    def settle(meshes, poses, up, category) -> list[dict]:
        results = drop_test_meshes(meshes, poses, up=up, categories=[category] * len(meshes), config=config)
        return [settling_check(r, config.drop_test, STAND_IN) for r in results]

    return settle
