"""A robot arm in the converted scene: merged into its MuJoCo world, drawn by its Gaussians.

config      RobotConfig: which robot (``panda`` or an MJCF path), where, how finely it is drawn
model       the robot's MJCF as a ``mujoco.MjSpec`` and what the rest needs to know of it
attach      the merge into ``scene.xml``'s world (``MjSpec`` attach), a stand under the base, the wrist camera
placement   the default base pose: beside the largest support, facing its centre, reach checked
appearance  each link's visual geoms as surface-aligned flat-disk Gaussians in the link's frame
kinematics  damped least-squares inverse kinematics on MuJoCo's Jacobians
script      the scripted pick-and-place: a plan of joint targets, run in any simulator
"""
