"""Physics priors and mass properties of a body made of convex parts.

Priors (paper): 0.3 kg unless a per-category table or the config says otherwise, friction
0.5, restitution 0. MuJoCo has no restitution coefficient: its contact is a damped spring
(``solref = (timeconst, dampratio)``); for a linear damped spring the rebound is
e = exp(−πζ/√(1−ζ²)), so ζ = −ln e / √(π² + ln² e), and restitution 0 is ζ = 1 (critical
damping, no bounce). URDF carries PyBullet's ``<restitution>`` and ``<lateral_friction>``.

Inertia comes from the collision geometry at uniform density: the density that gives the
prior mass to the parts' total volume, each part's exact polyhedral inertia (divergence
theorem over its hull triangles), summed about the common centre of mass. MJCF and URDF are
written from the same ``MassProperties`` so their centres of mass are the same.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from phirie_jax.construct.physics.collision import ConvexPart
from phirie_jax.construct.physics.config import PhysicsConfig


@dataclasses.dataclass(frozen=True)
class MassProperties:
    mass: float            # kg
    com: np.ndarray        # (3,) centre of mass, body frame, m
    inertia: np.ndarray    # (3, 3) inertia tensor about the centre of mass, body axes, kg m²
    volume: float          # m³ of the collision parts
    density: float         # kg / m³

    def principal(self) -> tuple[np.ndarray, np.ndarray]:
        """(3,) principal moments and (3, 3) their axes as columns (a proper rotation)."""
        moments, axes = np.linalg.eigh(self.inertia)
        if np.linalg.det(axes) < 0:
            axes[:, 2] *= -1
        return moments, axes

    def record(self) -> dict:
        return {"mass": self.mass, "com": self.com, "inertia": self.inertia, "volume": self.volume,
                "density": self.density}


@dataclasses.dataclass(frozen=True)
class Priors:
    mass: float
    friction: float
    restitution: float
    solref: tuple[float, float]
    solimp: tuple[float, ...]
    mass_source: str

    def record(self) -> dict:
        return dataclasses.asdict(self)


def damping_ratio(restitution: float) -> float:
    """MuJoCo damping ratio whose linear spring rebounds with this restitution (0 → 1)."""
    if restitution <= 0:
        return 1.0
    log_e = math.log(restitution)
    return -log_e / math.sqrt(math.pi**2 + log_e**2)


def priors(category: str | None, config: PhysicsConfig = PhysicsConfig()) -> Priors:
    table = dict(config.category_masses)
    if category is not None and category in table:
        mass, source = float(table[category]), f"category table ({category})"
    else:
        mass, source = config.mass, "config (paper default 0.3 kg)" if config.mass == 0.3 else "config"
    return Priors(mass, config.friction, config.restitution,
                  (config.contact_timeconst, damping_ratio(config.restitution)), tuple(config.solimp), source)


def _part_integrals(part: ConvexPart, scale: float) -> tuple[float, np.ndarray, np.ndarray]:
    """Volume, first moments (3,) and second moments ∫ x xᵀ (3, 3) of one closed part.

    Tetrahedra from the origin to each outward triangle; signed, so they sum to the solid."""
    tri = scale * part.vertices[part.faces]               # (F, 3, 3)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    det = np.einsum("ij,ij->i", a, np.cross(b, c))        # 6 × signed tetra volume
    volume = det.sum() / 6.0
    first = (det[:, None] * (a + b + c)).sum(0) / 24.0
    # ∫ x_i x_j over a tetra (0, a, b, c) = det/120 · (Σ_k v_k,i v_k,j + (Σ v)_i (Σ v)_j)
    s = a + b + c
    outer = np.einsum("fi,fj->fij", a, a) + np.einsum("fi,fj->fij", b, b) + np.einsum("fi,fj->fij", c, c)
    second = (det[:, None, None] * (outer + np.einsum("fi,fj->fij", s, s))).sum(0) / 120.0
    return float(volume), first, second


def mass_properties(parts: tuple[ConvexPart, ...] | list[ConvexPart], mass: float,
                    scale: float = 1.0) -> MassProperties:
    """Uniform-density mass properties of the union of ``parts`` (each scaled by ``scale``).

    Overlaps between parts count twice; CoACD's parts barely overlap."""
    volume, first, second = 0.0, np.zeros(3), np.zeros((3, 3))
    for part in parts:
        v, f, s = _part_integrals(part, scale)
        volume, first, second = volume + v, first + f, second + s
    if not volume > 0:
        raise ValueError(f"collision parts enclose no volume ({volume:.3g} m³)")
    density = mass / volume
    com = first / volume
    second_c = second - volume * np.outer(com, com)       # about the centre of mass
    inertia = density * (np.trace(second_c) * np.eye(3) - second_c)
    return MassProperties(float(mass), com, 0.5 * (inertia + inertia.T), float(volume), float(density))
