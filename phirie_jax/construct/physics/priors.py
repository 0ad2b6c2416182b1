"""Physics priors and mass properties of a body made of convex parts.

Priors (paper): friction 0.5, restitution 0; mass 0.3 kg unless something better is known.
The mass, most specific first (``Priors.mass_source`` says which):
1. ``--mass ID=KG`` (``PhysicsConfig.object_masses``);
2. ``PhysicsConfig.category_masses`` (the user's table);
3. the object's category (a mask's or a prompt's label) in ``CATEGORY_MATERIALS``, with its
   shape: a solid's density × its convex hull's volume, or a shell's (a mug, a bowl) material
   density × wall thickness × its surface (half the mesh's area: inner and outer faces). Each
   entry states where its numbers come from;
4. ``PhysicsConfig.mass`` (the paper's 0.3 kg).
A 16 cm bowl and a soup can are thereby no longer the same 0.3 kg.

MuJoCo has no restitution coefficient: its contact is a damped spring (``solref = (timeconst,
dampratio)``); for a linear damped spring the rebound is e = exp(−πζ/√(1−ζ²)), so ζ = −ln e / √(π² + ln² e), and restitution 0 is ζ = 1 (critical
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


@dataclasses.dataclass(frozen=True)
class Material:
    """How a category's mass follows from its shape. ``solid``: ``density`` × the convex hull's
    volume; ``shell``: ``density`` (the wall material's) × ``thickness`` × the surface."""

    kind: str          # "solid" | "shell"
    density: float     # kg / m³
    source: str
    thickness: float = 0.0   # m, shells


# Categories of tabletop objects. The solids' densities are YCB objects' published masses over the
# convex hulls of their scanned meshes (../data/ycb, measured with trimesh): mass per hull volume,
# so the air around a bottle's neck counts as it does for our completed meshes.
CATEGORY_MATERIALS = {
    "can": Material("solid", 977.0, "YCB 005 tomato soup can: 349 g over its scanned 357 cm³ hull"),
    "bottle": Material("solid", 863.0, "YCB 006 mustard bottle: 603 g over its scanned 699 cm³ hull"),
    "box": Material("solid", 178.0, "YCB 003 cracker box: 411 g over its scanned 2,310 cm³ hull"),
    "fruit": Material("solid", 800.0, "apple flesh, 0.8 g/cm³ (apples float)"),
    "mug": Material("shell", 2400.0, "stoneware (2.4 g/cm³) with 5 mm walls", 0.005),
    "bowl": Material("shell", 2400.0, "stoneware (2.4 g/cm³) with 5 mm walls", 0.005),
}
CATEGORY_SYNONYMS = {"cup": "mug", "soup can": "can", "tin": "can", "apple": "fruit", "orange": "fruit",
                     "lemon": "fruit", "pear": "fruit", "carton": "box", "cracker box": "box"}
MIN_MASS = 0.01  # kg: a measured shape never gives a body lighter than this


@dataclasses.dataclass(frozen=True)
class Shape:
    """What a category's material needs of an object: its surface and its convex hull's volume,
    in metres (the canonical mesh scaled by the pose's scale)."""

    area: float     # m² of the mesh's faces
    hull_volume: float  # m³

    @classmethod
    def of_mesh(cls, vertices: np.ndarray, faces: np.ndarray, scale: float = 1.0) -> Shape:
        """Of a mesh: (V, 3) vertices, (F, 3) triangle indices, times ``scale``."""
        from scipy.spatial import ConvexHull

        v = np.asarray(vertices, np.float64) * scale
        tri = v[np.asarray(faces)]
        area = 0.5 * float(np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())
        return cls(area, float(ConvexHull(v).volume))


def category_material(category: str | None) -> tuple[str, Material] | None:
    """(table key, material) of a category name (case and synonyms forgiven), or None."""
    if not category:
        return None
    key = category.strip().lower()
    key = CATEGORY_SYNONYMS.get(key, key)
    return (key, CATEGORY_MATERIALS[key]) if key in CATEGORY_MATERIALS else None


def prior_mass(category: str | None, config: PhysicsConfig, shape: Shape | None = None,
               object_id: int | None = None) -> tuple[float, str]:
    """(kg, where it came from): the module docstring's order."""
    given = dict(config.object_masses)
    if object_id is not None and object_id in given:
        return float(given[object_id]), f"given (--mass {object_id}={given[object_id]:g})"
    table = dict(config.category_masses)
    if category is not None and category in table:
        return float(table[category]), f"category table ({category})"
    found = category_material(category)
    if found is not None and shape is not None:
        key, m = found
        if m.kind == "solid":
            mass = m.density * shape.hull_volume
            how = f"{m.density:g} kg/m³ × {1e6 * shape.hull_volume:.0f} cm³ hull"
        else:
            mass = m.density * m.thickness * 0.5 * shape.area
            how = f"{m.density:g} kg/m³ × {1000 * m.thickness:g} mm × {1e4 * 0.5 * shape.area:.0f} cm² wall"
        return max(mass, MIN_MASS), f"category {key}: {how} ({m.source})"
    return config.mass, "config (paper default 0.3 kg)" if config.mass == 0.3 else "config"


def priors(category: str | None, config: PhysicsConfig = PhysicsConfig(), shape: Shape | None = None,
           object_id: int | None = None) -> Priors:
    mass, source = prior_mass(category, config, shape, object_id)
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
