"""The robot's MJCF as a ``mujoco.MjSpec``, and what the rest needs to know of it.

``robot_spec(model)`` reads ``"panda"`` — the Franka Panda (Apache-2.0, V. Kumar) shipped as include
files in the ``gymnasium-robotics`` wheel, compiled through a wrapper as docs/architecture.md "Robot model"
describes — or any MJCF file. ``describe(spec)`` finds its root body, end-effector site, arm
joints with their position servos, gripper joints and actuators (slide joints under the hand,
open at the top of their control range) and a home configuration; ``RobotDescription`` records
them by the names they have before the merge (``attach`` prefixes them).
"""

from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path

import numpy as np

from phirie_jax.errors import SceneInputError

PANDA = "panda"
PANDA_FOLDER = ("envs", "assets", "kitchen_franka", "franka_assets")
PANDA_HOME = (0.0, -0.785, 0.0, -2.356, 0.0, 0.0, 0.0)   # forearm over the base, hand down
PANDA_SITE = "end_effector"
# the Panda's wrist camera: on the hand (link 7's frame), 2 cm off the hand's side across the
# fingers' travel (the hand is 6.4 cm thick there), looking at the point between the fingertips
PANDA_WRIST = ("panda0_link7", (0.0368, -0.0368, 0.12), (0.0, 0.0, 0.25))
END_EFFECTOR_WORDS = ("end_effector", "attachment", "tcp", "grip", "pinch", "ee")
MISSING_PANDA = ("needs the gymnasium-robotics package, which ships the Franka Panda model: "
                 "pip install 'phirie_jax[robot]'")


@dataclasses.dataclass(frozen=True)
class RobotDescription:
    """The parts of a robot model the environment drives (names as in the robot's own MJCF)."""

    name: str
    root_body: str
    end_effector: str                  # site
    arm_joints: tuple[str, ...]        # hinge/slide joints IK moves, in chain order
    arm_actuators: tuple[str, ...]     # the position servo of each arm joint
    gripper_joints: tuple[str, ...]
    gripper_actuators: tuple[str, ...]
    home: tuple[float, ...]            # (len(arm_joints),) arm configuration at reset
    # wrist camera: (body, position and target point in the body's frame); None: on the end
    # effector's body, behind the site, looking along the site's z
    wrist: tuple[str, tuple[float, float, float], tuple[float, float, float]] | None = None


def panda_folder() -> Path:
    """The ``franka_assets`` folder inside the installed ``gymnasium-robotics`` (found without
    importing the package, whose import prints notices)."""
    found = importlib.util.find_spec("gymnasium_robotics")
    if found is None or not found.submodule_search_locations:
        raise SceneInputError(None, f"robot '{PANDA}'", MISSING_PANDA)
    folder = Path(list(found.submodule_search_locations)[0]).joinpath(*PANDA_FOLDER)
    if not (folder / "chain.xml").is_file():
        raise SceneInputError(folder, None, "missing chain.xml (expected gymnasium-robotics 1.4's Franka "
                                            "assets: pip install 'phirie_jax[robot]')")
    return folder


def panda_spec():
    """The Panda of ``gymnasium-robotics`` as one spec: 11 bodies, 9 joints, 9 position servos."""
    import mujoco

    folder = panda_folder()
    wrapper = f"""<mujoco model="{PANDA}">
  <compiler angle="radian" inertiafromgeom="auto" inertiagrouprange="3 5"/>
  <include file="{folder / 'assets.xml'}"/>
  <include file="{folder / 'actuator.xml'}"/>
  <worldbody><include file="{folder / 'chain.xml'}"/></worldbody>
</mujoco>"""
    spec = mujoco.MjSpec.from_string(wrapper)
    # included meshes resolve against the include's folder, not its meshdir: point them there
    for mesh in spec.meshes:
        mesh.file = str(folder / "meshes" / Path(mesh.file).relative_to(folder))
    return spec


def robot_spec(model: str):
    """``(spec, description)`` of ``"panda"`` or an MJCF file; bad input is one ``SceneInputError`` line."""
    import mujoco

    if model == PANDA:
        spec = panda_spec()
        return spec, describe(spec, PANDA, PANDA_SITE, PANDA_HOME, PANDA_WRIST)
    path = Path(model)
    if not path.is_file():
        raise SceneInputError(path, None, f"no such file (expected '{PANDA}' or the path of a robot's MJCF file)")
    try:
        spec = mujoco.MjSpec.from_file(str(path))
        spec.compile()
    except Exception as err:  # noqa: BLE001 — MuJoCo's message names the problem
        raise SceneInputError(path, None, f"MuJoCo cannot compile it: {_one_line(err)}") from None
    return spec, describe(spec, path.stem)


def _one_line(err: Exception) -> str:
    return " ".join(str(err).split())


def describe(spec, name: str, end_effector: str | None = None, home=None, wrist=None) -> RobotDescription:
    """What the environment drives in a robot spec (module docstring); ``SceneInputError`` when the
    robot has no single root body, no end-effector site or an arm joint without a position servo."""
    import mujoco

    where = Path(spec.modelfiledir or ".") / (spec.modelname or name)
    roots = list(spec.worldbody.bodies)
    if len(roots) != 1:
        raise SceneInputError(where, "worldbody", f"{len(roots)} top-level bodies (expected one robot root body)")
    model = spec.compile()
    sites = [model.site(i).name for i in range(model.nsite)]
    if end_effector is None:
        named = [s for s in sites if any(w in s.lower() for w in END_EFFECTOR_WORDS)]
        if len(named) != 1:
            raise SceneInputError(where, "site", f"no single end-effector site among {sites} (expected one "
                                                 "named like 'end_effector' or 'tcp', or RobotConfig.end_effector)")
        end_effector = named[0]
    if end_effector not in sites:
        raise SceneInputError(where, f"site '{end_effector}'", f"missing (the model's sites: {sites})")
    hand = int(model.site_bodyid[model.site(end_effector).id])
    in_hand = set(_subtree(model, hand))
    hinge, slide = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)
    joints = [j for j in range(model.njnt) if int(model.jnt_type[j]) in (hinge, slide)]
    gripper = [j for j in joints if model.jnt_bodyid[j] in in_hand and int(model.jnt_type[j]) == slide]
    arm = [j for j in joints if j not in gripper]
    servo = _position_servos(model)
    missing = [model.joint(j).name for j in arm if j not in servo]
    if missing:
        raise SceneInputError(where, f"joint '{missing[0]}'", "has no position actuator (expected a position "
                                                              "servo on every arm joint)")
    gripper_actuators = sorted({a for a in range(model.nu) if _drives(model, a, gripper)})
    if home is None:
        home = _home(model, arm)
    return RobotDescription(
        name=name, root_body=roots[0].name, end_effector=end_effector,
        arm_joints=tuple(model.joint(j).name for j in arm), arm_actuators=tuple(model.actuator(servo[j]).name for j in arm),
        gripper_joints=tuple(model.joint(j).name for j in gripper),
        gripper_actuators=tuple(model.actuator(a).name for a in gripper_actuators),
        home=tuple(float(v) for v in home), wrist=wrist)


def _subtree(model, body: int) -> list[int]:
    return [b for b in range(model.nbody) if _ancestor(model, body, b)]


def _ancestor(model, ancestor: int, body: int) -> bool:
    while body > 0:
        if body == ancestor:
            return True
        body = int(model.body_parentid[body])
    return ancestor == 0


def _position_servos(model) -> dict[int, int]:
    """joint id → the actuator that servos its position (joint transmission, gain = −bias)."""
    import mujoco

    servos = {}
    for a in range(model.nu):
        if int(model.actuator_trntype[a]) != int(mujoco.mjtTrn.mjTRN_JOINT):
            continue
        kp, bias = model.actuator_gainprm[a, 0], model.actuator_biasprm[a, 1]
        if kp > 0 and np.isclose(bias, -kp):
            servos.setdefault(int(model.actuator_trnid[a, 0]), a)
    return servos


def _drives(model, actuator: int, joints: list[int]) -> bool:
    """Whether an actuator moves one of ``joints`` (directly or through a fixed tendon)."""
    import mujoco

    target = int(model.actuator_trnid[actuator, 0])
    kind = int(model.actuator_trntype[actuator])
    if kind == int(mujoco.mjtTrn.mjTRN_JOINT):
        return target in joints
    if kind == int(mujoco.mjtTrn.mjTRN_TENDON):
        start, count = model.tendon_adr[target], model.tendon_num[target]
        return any(int(model.wrap_objid[w]) in joints for w in range(start, start + count)
                   if int(model.wrap_type[w]) == int(mujoco.mjtWrap.mjWRAP_JOINT))
    return False


def _home(model, arm: list[int]) -> np.ndarray:
    """A keyframe named ``home``, else 0 moved into each joint's range."""
    for k in range(model.nkey):
        if model.key(k).name == "home":
            return np.array([model.key_qpos[k, model.jnt_qposadr[j]] for j in arm])
    low, high = model.jnt_range[arm, 0], model.jnt_range[arm, 1]
    limited = model.jnt_limited[arm].astype(bool)
    return np.where(limited, np.clip(0.0, low, high), 0.0)
