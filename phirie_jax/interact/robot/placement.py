"""Where the robot stands: beside the largest support, facing its centre, where it reaches the most objects.

The supports are ``scene.xml``'s world geoms: the floor plane and a box per support surface
(``construct.physics.supports``). Candidate bases lie along the four edges of the largest box's
top, just outside it (the root body's footprint clears the edge by ``EDGE_CLEARANCE``), at the
box's top height (the robot stands on a stand, ``attach``), each turned to face the box's centre.
Without a box the objects' footprint on the floor, grown by ``FLOOR_MARGIN``, stands in for it.

Reach: the arm's radial reach band for a top-down grasp at the support's height is measured once
with inverse kinematics on the robot alone (``reach_band``); the candidate with the most objects
inside the band wins (ties: the smallest summed distance). The chosen base is then checked
object by object with inverse kinematics (``reachable``) and the result recorded.

``check_clear`` refuses a base whose robot, at its home pose, sinks into a support or an object.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.interact.robot.attach import STAND, STAND_MARGIN, Base
from phirie_jax.interact.robot.kinematics import Kinematics

EDGE_CLEARANCE = 0.03      # m between the support's edge and the robot's footprint
EDGE_POSITIONS = 7         # candidate bases along each edge
FLOOR_MARGIN = 0.15        # m: the objects' footprint grown by this when there is no support box
GRASP_HEIGHT = 0.05        # m above the support: where the reach band is measured
APPROACH = 0.12            # m: a grasp is reachable when the pose this far above it is too
PENETRATION_TOL = 0.002    # m: deeper contact of the robot with the scene at home refuses the base
TOP_DOWN = np.diag([1.0, -1.0, -1.0])   # site axes: x along the scene's x, z pointing down


@dataclasses.dataclass(frozen=True)
class Support:
    """A support's top face: centre (3,), its two horizontal axes (2, 3), half extents (2,)."""

    name: str
    centre: np.ndarray
    axes: np.ndarray
    half: np.ndarray

    @property
    def area(self) -> float:
        return float(4 * self.half[0] * self.half[1])


@dataclasses.dataclass(frozen=True)
class Placement:
    """The chosen base and what it reaches (object ids)."""

    base: Base
    support: str
    reachable: tuple[int, ...]
    unreachable: tuple[int, ...]
    source: str                      # "default" or "given"

    def record(self) -> dict:
        return {**self.base.record(), "support": self.support, "reachable": list(self.reachable),
                "unreachable": list(self.unreachable), "source": self.source}


def scene_supports(model, data) -> tuple[float, list[Support]]:
    """The floor plane's height and every box support's top face, from a compiled scene."""
    import mujoco

    floor, boxes = 0.0, []
    for g in range(model.ngeom):
        if model.geom_bodyid[g] != 0:
            continue
        rot = data.geom_xmat[g].reshape(3, 3)
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE:
            floor = float(data.geom_xpos[g][2])
        elif model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
            size = model.geom_size[g]
            centre = data.geom_xpos[g] + rot[:, 2] * size[2]
            boxes.append(Support(model.geom(g).name, centre, rot[:, :2].T.copy(), size[:2].copy()))
    return floor, boxes


def object_centres(model, data, body_ids: list[int]) -> np.ndarray:
    """(K, 3) centre of each body's collision vertices (x, y) at the height of their top (z)."""
    from phirie_jax.interact.mjx_model import body_frame_vertices

    out = []
    for b in body_ids:
        verts = body_frame_vertices(model, b) @ data.xmat[b].reshape(3, 3).T + data.xpos[b]
        lo, hi = verts.min(0), verts.max(0)
        out.append([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), hi[2]])
    return np.asarray(out).reshape(-1, 3)


def reach_band(kinematics: Kinematics, home, height: float, step: float = 0.02) -> tuple[float, float]:
    """(min, max) horizontal distance from the base at which a top-down pose at ``height`` above the
    base, and the pose ``APPROACH`` above it, are reachable (scanned along the base's +x)."""
    radii = np.arange(0.1, 1.6, step)
    ok = [kinematics.solve([r, 0.0, height], TOP_DOWN, q0=home).converged
          and kinematics.solve([r, 0.0, height + APPROACH], TOP_DOWN, q0=home).converged for r in radii]
    if not any(ok):
        return 0.0, 0.0
    hits = radii[np.asarray(ok)]
    return float(hits.min()), float(hits.max())


def _candidates(support: Support, low: np.ndarray, high: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """(position (3,), yaw) along the four edges, facing the centre; the root's footprint is
    ``low``..``high`` (2,) in its own frame, whose +x faces the centre."""
    margin = STAND_MARGIN
    corners = np.array([[x, y] for x in (low[0] - margin, high[0] + margin) for y in (low[1] - margin, high[1] + margin)])
    out = []
    for axis in range(2):
        for sign in (-1.0, 1.0):
            outward = sign * support.axes[axis]
            along = support.axes[1 - axis]
            edge = support.centre + outward * support.half[axis]
            for f in np.linspace(-0.75, 0.75, EDGE_POSITIONS):
                on_edge = edge + along * f * support.half[1 - axis]
                p = on_edge + outward * (high[0] + EDGE_CLEARANCE)
                for _ in range(2):  # the footprint turned to face the centre: clear the edge by its reach
                    yaw = float(np.arctan2(*(support.centre - p)[1::-1]))
                    c, s = np.cos(yaw), np.sin(yaw)
                    turned = corners @ np.array([[c, s], [-s, c]])
                    p = on_edge + outward * (float(np.max(turned @ -outward[:2])) + EDGE_CLEARANCE)
                out.append((p, float(np.arctan2(*(support.centre - p)[1::-1]))))
    return out


def default_base(floor: float, supports: list[Support], centres: np.ndarray, band: tuple[float, float],
                 low: np.ndarray, high: np.ndarray) -> tuple[Base, str]:
    """The base beside the largest support that reaches the most object ``centres`` (K, 3)."""
    if supports:
        support = max(supports, key=lambda s: s.area)
    else:
        xy = centres[:, :2] if len(centres) else np.zeros((1, 2))
        lo, hi = xy.min(0) - FLOOR_MARGIN, xy.max(0) + FLOOR_MARGIN
        support = Support("floor", np.array([*(0.5 * (lo + hi)), floor]), np.eye(3)[:2], 0.5 * (hi - lo))
    best, best_key = None, None
    for position, yaw in _candidates(support, low, high):
        dist = np.linalg.norm(centres[:, :2] - position[:2], axis=1)
        count = int(np.sum((dist >= band[0]) & (dist <= band[1])))
        key = (count, -float(dist.sum()))
        if best_key is None or key > best_key:
            best, best_key = Base(position, yaw), key
    return best, support.name


def reachable(kinematics: Kinematics, home, base: Base, centres: np.ndarray) -> np.ndarray:
    """(K,) whether a top-down grasp at each centre's height, and its approach above, are reachable."""
    inverse = np.linalg.inv(base.matrix)
    down = inverse[:3, :3] @ TOP_DOWN
    out = []
    for c in centres:
        local = inverse[:3, :3] @ c + inverse[:3, 3]
        out.append(kinematics.solve(local, down, q0=home).converged
                   and kinematics.solve(local + [0, 0, APPROACH], down, q0=home).converged)
    return np.asarray(out, bool)


def check_clear(model, data, robot_bodies: set[int], where, base: Base) -> None:
    """``SceneInputError`` when a colliding robot geom (the stand included) sinks more than
    ``PENETRATION_TOL`` into a colliding geom of the scene (``data`` holds the home pose after
    ``mj_forward``). Signed distances (``mj_geomDistance``), not contacts: the robot's base is
    welded to the world, and MuJoCo makes no contacts between two geoms of the world."""
    import mujoco

    colliding = [g for g in range(model.ngeom) if model.geom_contype[g] or model.geom_conaffinity[g]]
    mine = [g for g in colliding if int(model.geom_bodyid[g]) in robot_bodies]
    scene = [g for g in colliding if int(model.geom_bodyid[g]) not in robot_bodies]
    stand = next((g for g in range(model.ngeom) if model.geom(g).name == STAND), -1)
    worst = None
    for g in mine:
        for other in scene:
            if g == stand and model.geom_type[other] == mujoco.mjtGeom.mjGEOM_PLANE:
                continue  # the stand stands on the floor
            depth = -mujoco.mj_geomDistance(model, data, g, other, PENETRATION_TOL, None)
            if depth > PENETRATION_TOL and (worst is None or depth > worst[1]):
                worst = (model.geom(other).name or f"geom {other}", depth)
    if worst is not None:
        x, y, z = base.position
        raise SceneInputError(where, "robot base", f"({x:.3f}, {y:.3f}, {z:.3f}, yaw {np.degrees(base.yaw):.0f}°) "
                              f"puts the robot {100 * worst[1]:.1f} cm into {worst[0]} (expected a base clear of "
                              "the scene's supports and objects)")
