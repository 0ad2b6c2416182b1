"""The Interactive Environment: the simulator moves the bodies, the same Gaussians follow.

``Environment.load(OUT_DIR)`` reads a converted scene: the MuJoCo model (``scene.xml``),
the background Gaussians (``background.ply``), each accepted object's visual Gaussians
(``objects/<id>/visual.ply``, canonical frame) and S_i(0) (the manifest's ``pose``), and
the capture's cameras (``cameras.json``/``transforms.json`` written beside them).

At time t the object's Gaussians are placed by S_i(t) = T_i(t) T_i(0)⁻¹ S_i(0), with T_i
the simulated pose of its body; means, covariances and SH coefficients are transformed
(``kernels.gaussians.transform_bodies``) and everything — background and every object —
is rasterized together, in one depth order (no image pasting).

Interactions: ``shoot`` (an impulse along the ray through a camera pixel, ray-cast
against the collision geometry), ``push`` (a kinematic pusher body driven along a
line), ``place`` (drop or throw: set a body's pose and velocity).

A robot (``load(robot=...)``, ``phirie_jax.interact.robot``) is merged into the MuJoCo world
with ``MjSpec`` attach; each of its links carries Gaussians in its own frame and joins the
body-attached set after the objects (``objects`` lists both: a link has ``id`` None), so every
renderer path draws it like an object. Cameras: the capture's (by index or image name), the
MJCF's and those on bodies (the robot's ``wrist``), by name, posed from the current state.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from kernels.gaussians import Gaussians, Sim3, concatenate, transform_bodies
from phirie_jax import layout
from phirie_jax.construct.physics.body import body_name
from phirie_jax.errors import SceneInputError
from phirie_jax.interact.robot.appearance import robot_gaussians
from phirie_jax.io.ply import read_gaussian_ply
from phirie_jax.io.transforms_json import read_transforms_json
from phirie_jax.manifest import Manifest
from phirie_jax.rotations import matrix_to_quat, pose_matrix
from phirie_jax.types import Camera, GaussianSplatData

PUSHER = "pusher"
ROBOT_PREFIX = "robot/"           # the merged robot's names (``robot.attach.PREFIX``)
MJCF_CAMERA_SIZE = (160, 120)     # image size of an MJCF camera without a robot config
PUSHER_HALF_SIZE = (0.02, 0.05, 0.03)  # a paddle: thin along the push direction


@dataclasses.dataclass(frozen=True)
class SceneObject:
    """One body with Gaussians attached: a simulated object, or a robot link (``id`` None), and
    where its Gaussians' frame was at t = 0 (a link's Gaussians are in its body frame)."""

    id: int | None            # object id; None for a robot link
    body: str                 # MuJoCo body name
    body_id: int
    pose0: np.ndarray         # (4, 4) S_i(0): canonical → scene
    gaussians: slice          # this object's rows in the environment's object Gaussians


@jax.jit
def compose_scene(background: Gaussians, objects: Gaussians, body, placements) -> Gaussians:
    """Background plus every object Gaussian moved by its body's placement (K, 4, 4)."""
    moved = transform_bodies(objects, Sim3.from_matrix(placements), body)
    return concatenate([background, moved])


def load_spec(out_dir: Path, with_pusher: bool = False):
    """The ``scene.xml`` of a converted folder as a ``mujoco.MjSpec`` (plus the pusher body)."""
    import mujoco

    path = out_dir / layout.SCENE_MJCF
    if not path.is_file():
        raise SceneInputError(path, None, "missing (expected the physics stage's MJCF scene; "
                                          "run `phirie convert` first)")
    try:
        spec = mujoco.MjSpec.from_file(str(path))
    except Exception as err:  # noqa: BLE001 — MuJoCo's own message names the problem
        raise SceneInputError(path, None, f"MuJoCo cannot load it: {err}") from None
    if with_pusher:
        body = spec.worldbody.add_body(name=PUSHER, mocap=True, pos=[0.0, 0.0, -10.0])
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=list(PUSHER_HALF_SIZE), rgba=[0.2, 0.2, 0.2, 1])
    return spec


def _compile(spec, out_dir: Path):
    try:
        return spec.compile()
    except Exception as err:  # noqa: BLE001
        raise SceneInputError(out_dir / layout.SCENE_MJCF, None, f"MuJoCo cannot load it: {err}") from None


def load_cameras(out_dir: Path) -> list[Camera]:
    path = out_dir / layout.CAMERAS
    return read_transforms_json(path) if path.is_file() else []


class Environment:
    """One simulated world whose Gaussians follow its bodies (module docstring)."""

    def __init__(self, out_dir: Path, model, background: GaussianSplatData,
                 objects: list[tuple[int, np.ndarray, GaussianSplatData]], cameras: list[Camera],
                 robot=None, spec=None):
        """``robot``: the merged robot (``robot.setup.Robot``) or None; ``spec``: the ``MjSpec``
        ``model`` was compiled from, when known (``spec()``)."""
        import mujoco

        self.out_dir = Path(out_dir)
        self.with_pusher = False  # whether ``model`` carries the pusher body (``load``)
        self.robot = robot
        self._spec = spec
        self.model = model
        self.data = mujoco.MjData(model)
        self.cameras = cameras
        self.objects: list[SceneObject] = []
        parts, body, start = [], [], 0
        for index, (object_id, pose0, splats) in enumerate(objects):
            name = body_name(object_id)
            body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
            if body_id < 0:
                raise SceneInputError(self.out_dir / layout.SCENE_MJCF, f"body '{name}'",
                                      "missing (expected one free body per accepted object)")
            self.objects.append(SceneObject(object_id, name, body_id, np.asarray(pose0, np.float64),
                                            slice(start, start + splats.num)))
            parts.append(splats.to_host_kernel())
            body.append(np.full(splats.num, index, np.int32))
            start += splats.num
        if robot is not None:
            self.reset()  # a link's Gaussians are in its frame: its pose at home is its pose0
            for body_id, splats in robot_gaussians(model, list(robot.bodies), robot.config.spacing,
                                                   robot.config.shading, robot.config.seed):
                if splats.sh_degree != background.sh_degree:
                    splats = _match_degree(splats, background.sh_degree)
                pose0 = pose_matrix(self.data.xpos[body_id], self.data.xquat[body_id])
                body.append(np.full(splats.num, len(self.objects), np.int32))
                self.objects.append(SceneObject(None, model.body(body_id).name, body_id, pose0,
                                                slice(start, start + splats.num)))
                parts.append(splats.to_host_kernel())
                start += splats.num
        self.background = background.to_kernel()
        if not parts:   # an empty set of the background's layout
            parts = [jax.tree.map(lambda x: np.zeros((0,) + x.shape[1:], np.float32), self.background)]
        self.object_gaussians = jax.device_put(concatenate(parts))   # joined on the host, moved once
        self.body_index = jnp.asarray(np.concatenate(body) if body else np.zeros(0, np.int32))
        self.reset()

    # --- loading ---------------------------------------------------------------------

    @classmethod
    def load(cls, out_dir: str | Path, with_pusher: bool = False, robot=None) -> "Environment":
        """Read a converted scene folder (``phirie convert`` output).

        ``robot``: None, a model name or MJCF path (``"panda"``), or a ``RobotConfig``: the robot
        is merged into the scene's world (``phirie_jax.interact.robot``).
        """
        out_dir = Path(out_dir)
        manifest_path = out_dir / "manifest.json"
        if not manifest_path.is_file():
            raise SceneInputError(manifest_path, None, "missing (expected a `phirie convert` output folder)")
        bodies = [o for o in Manifest.load(out_dir).kept_objects() if o.visual and o.collision]
        spec = load_spec(out_dir, with_pusher)
        handle = None
        if robot is not None:
            from phirie_jax.interact.robot.config import RobotConfig
            from phirie_jax.interact.robot.setup import merge_robot

            config = robot if isinstance(robot, RobotConfig) else RobotConfig(model=str(robot))
            model, handle = merge_robot(spec, config, out_dir / layout.SCENE_MJCF,
                                        {o.id: body_name(o.id) for o in bodies})
        else:
            model = _compile(spec, out_dir)
        if not (out_dir / layout.BACKGROUND).is_file():
            raise SceneInputError(out_dir / layout.BACKGROUND, None, "missing (expected the background stage's PLY)")
        background = read_gaussian_ply(out_dir / layout.BACKGROUND)
        objects = []
        for obj in bodies:
            splats = read_gaussian_ply(out_dir / obj.visual)
            if splats.sh_degree != background.sh_degree:
                splats = _match_degree(splats, background.sh_degree)
            objects.append((obj.id, np.asarray(obj.pose, np.float64), splats))
        env = cls(out_dir, model, background, objects, load_cameras(out_dir), robot=handle, spec=spec)
        env.with_pusher = with_pusher
        return env

    def spec(self):
        """A copy of the ``MjSpec`` the model was compiled from (robot and pusher included)."""
        if self._spec is None:
            raise RuntimeError("this environment was built from a compiled model only")
        return self._spec.copy()

    # --- simulation ------------------------------------------------------------------

    def reset(self) -> None:
        import mujoco

        mujoco.mj_resetData(self.model, self.data)
        if self.robot is not None:
            self.robot.set_home(self.model, self.data)
        mujoco.mj_forward(self.model, self.data)
        self._pose_t0 = self.body_poses()

    @property
    def time(self) -> float:
        return float(self.data.time)

    @property
    def timestep(self) -> float:
        return float(self.model.opt.timestep)

    def step(self, steps: int = 1) -> None:
        import mujoco

        mujoco.mj_step(self.model, self.data, nstep=int(steps))

    def body_poses(self) -> np.ndarray:
        """(K, 4, 4) current world poses T_i(t) of the object bodies."""
        ids = [o.body_id for o in self.objects]
        return pose_matrix(self.data.xpos[ids], self.data.xquat[ids])

    def placements(self) -> np.ndarray:
        """(K, 4, 4) S_i(t) = T_i(t) T_i(0)⁻¹ S_i(0): canonical frame → scene, now."""
        if not self.objects:
            return np.zeros((0, 4, 4))
        pose0 = np.stack([o.pose0 for o in self.objects])
        return self.body_poses() @ np.linalg.inv(self._pose_t0) @ pose0

    def object(self, object_id: int) -> SceneObject:
        for o in self.objects:
            if o.id == object_id:
                return o
        raise KeyError(f"no simulated object with id {object_id}")

    # --- rendering -------------------------------------------------------------------

    def gaussians(self) -> Gaussians:
        """All Gaussians of the scene, objects placed at their current poses."""
        placements = jnp.asarray(self.placements(), jnp.float32).reshape(-1, 4, 4)
        return compose_scene(self.background, self.object_gaussians, self.body_index, placements)

    def camera_names(self) -> list[str]:
        """Names ``camera`` takes: the MJCF's cameras (the robot's without its prefix), then the
        capture's image names."""
        names = [self.model.camera(i).name for i in range(self.model.ncam)]
        return [n.removeprefix(ROBOT_PREFIX) for n in names] + [c.name for c in self.cameras]

    def camera(self, camera: Camera | int | str) -> Camera:
        """A camera record: as given, the capture's k-th, or by name (``camera_names``): an MJCF
        camera is posed by the current state (a camera on a body moves with it)."""
        if isinstance(camera, Camera):
            return camera
        if isinstance(camera, str):
            return self._named_camera(camera)
        if not 0 <= camera < len(self.cameras):
            raise SceneInputError(self.out_dir / layout.CAMERAS, "camera",
                                  f"{camera} (expected 0..{len(self.cameras) - 1})")
        return self.cameras[camera]

    def render(self, camera: Camera | int, background=(0.0, 0.0, 0.0), width: int | None = None):
        """rgb / depth / alpha of the current state from one camera (``phirie_jax.render``)."""
        from phirie_jax.render import render

        cam = self.camera(camera)
        if width is not None:
            cam = cam.scaled(width / cam.width)
        return render(self.gaussians(), cam, background=np.asarray(background, np.float32))

    def _named_camera(self, name: str) -> Camera:
        import mujoco

        for candidate in (name, ROBOT_PREFIX + name):
            cam = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, candidate)
            if cam >= 0:
                size = self.robot.config.camera_size if self.robot is not None else MJCF_CAMERA_SIZE
                return mjcf_camera(self.model, self.data, cam, *size)
        for c in self.cameras:
            if c.name == name:
                return c
        raise SceneInputError(self.out_dir / layout.CAMERAS, "camera", f"'{name}' (expected one of {self.camera_names()})")

    # --- interactions ----------------------------------------------------------------

    def ray(self, camera: Camera | int, pixel) -> tuple[np.ndarray, np.ndarray]:
        """World origin and unit direction of the ray through pixel (u, v) (pixel-centre convention)."""
        cam = self.camera(camera)
        direction_cam = np.linalg.solve(cam.K, np.array([pixel[0], pixel[1], 1.0]))
        rot = cam.world_to_camera[:3, :3]
        direction = rot.T @ direction_cam
        return cam.center, direction / np.linalg.norm(direction)

    def cast(self, origin, direction) -> tuple[int | None, np.ndarray | None]:
        """First collision geometry along a ray: (object id or None, hit point or None)."""
        import mujoco

        geom = np.zeros(1, np.int32)
        distance = mujoco.mj_ray(self.model, self.data, np.asarray(origin, np.float64),
                                 np.asarray(direction, np.float64), None, 1, -1, geom)
        if distance < 0:
            return None, None
        point = np.asarray(origin) + distance * np.asarray(direction)
        body = int(self.model.geom_bodyid[geom[0]])
        for o in self.objects:
            if o.body_id == body:
                return o.id, point
        return None, point

    def apply_impulse(self, object_id: int, point, impulse) -> None:
        """Instantaneous impulse (N·s, world frame) at a world point: Δq̇ = M⁻¹ Jᵀ p."""
        import mujoco

        body = self.object(object_id).body_id
        jacp = np.zeros((3, self.model.nv))
        mujoco.mj_jac(self.model, self.data, jacp, None, np.asarray(point, np.float64), body)
        generalized = (jacp.T @ np.asarray(impulse, np.float64))[None, :]  # (1, nv)
        delta = np.zeros_like(generalized)
        mujoco.mj_solveM(self.model, self.data, delta, generalized)
        self.data.qvel[:] += delta[0]
        mujoco.mj_forward(self.model, self.data)

    def shoot(self, camera: Camera | int, pixel, speed: float = 1.5) -> dict:
        """Hit whatever object the ray through ``pixel`` meets first, giving it ``speed`` (m/s)
        along the ray (impulse = mass × speed at the hit point). Returns what was hit."""
        origin, direction = self.ray(camera, pixel)
        object_id, point = self.cast(origin, direction)
        if object_id is None:
            return {"hit": None, "point": None if point is None else point.tolist()}
        mass = float(self.model.body_subtreemass[self.object(object_id).body_id])
        self.apply_impulse(object_id, point, mass * speed * direction)
        return {"hit": object_id, "point": point.tolist(), "impulse": (mass * speed * direction).tolist()}

    def place(self, object_id: int, pose: np.ndarray | None = None, linear_velocity=None,
              angular_velocity=None) -> None:
        """Drop or throw: set a body's world pose (4×4 rigid) and/or velocity (world frame)."""
        import mujoco

        body = self.object(object_id).body_id
        joint = int(self.model.body_jntadr[body])
        qpos, qvel = int(self.model.jnt_qposadr[joint]), int(self.model.jnt_dofadr[joint])
        if pose is not None:
            pose = np.asarray(pose, np.float64)
            self.data.qpos[qpos:qpos + 3] = pose[:3, 3]
            self.data.qpos[qpos + 3:qpos + 7] = matrix_to_quat(pose[:3, :3])
        if linear_velocity is not None:
            self.data.qvel[qvel:qvel + 3] = linear_velocity
        if angular_velocity is not None:  # free joints keep angular velocity in the body frame
            rot = pose_matrix(self.data.xpos[body], self.data.xquat[body])[:3, :3]
            self.data.qvel[qvel + 3:qvel + 6] = rot.T @ np.asarray(angular_velocity, np.float64)
        mujoco.mj_forward(self.model, self.data)

    def push(self, start, end, seconds: float, on_step=None) -> None:
        """Drive the kinematic pusher (``load(with_pusher=True)``) from ``start`` to ``end``."""
        import mujoco

        body = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, PUSHER)
        if body < 0:
            raise RuntimeError("this environment has no pusher: load it with with_pusher=True")
        mocap = int(self.model.body_mocapid[body])
        steps = max(1, int(round(seconds / self.timestep)))
        start, end = np.asarray(start, np.float64), np.asarray(end, np.float64)
        for i in range(steps):
            self.data.mocap_pos[mocap] = start + (end - start) * (i + 1) / steps
            mujoco.mj_step(self.model, self.data)
            if on_step is not None:
                on_step(i)
        self.data.mocap_pos[mocap] = [0.0, 0.0, -10.0]


def mjcf_camera(model, data, camera: int, width: int, height: int) -> Camera:
    """A MuJoCo camera (looks along −z, y up, vertical ``fovy``) as a pinhole ``Camera`` record
    (OpenCV axes: x right, y down, z forward), posed from ``data``."""
    rot = data.cam_xmat[camera].reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])
    world_to_camera = np.eye(4)
    world_to_camera[:3, :3] = rot.T
    world_to_camera[:3, 3] = -rot.T @ data.cam_xpos[camera]
    focal = 0.5 * height / np.tan(0.5 * np.radians(model.cam_fovy[camera]))
    K = np.array([[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]])
    return Camera(model.camera(camera).name, K, world_to_camera, int(width), int(height))


def _match_degree(splats: GaussianSplatData, degree: int) -> GaussianSplatData:
    """Pad (with zeros) or truncate SH bands so every set rasterizes together."""
    k = (degree + 1) ** 2
    sh = splats.sh[:, :k]
    if sh.shape[1] < k:
        sh = np.concatenate([sh, np.zeros((splats.num, k - sh.shape[1], 3), sh.dtype)], axis=1)
    return dataclasses.replace(splats, sh=sh, layout=())
