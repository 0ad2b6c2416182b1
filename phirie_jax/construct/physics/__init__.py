"""Simulator assets and drop tests.

stage       run_physics (the stage) and run_droptest (re-run on an exported folder)
config      PhysicsConfig (with DropTestConfig)
collision   mesh repair, CoACD convex decomposition, hull fallback (MeshError for bad meshes)
priors      physics priors (mass, friction, restitution → solref) and mass properties
supports    support geoms (floor plane, tabletop boxes) fitted from the scene surface
export      collision part OBJs, object.urdf, scene.xml (MJCF), a free settle of the scene
droptest    the paper's drop-test protocol; MuJoCo C reference; the object stage's settling hook
mjx_batch   every drop test of a bucket in one vmapped, jitted MJX program
"""
