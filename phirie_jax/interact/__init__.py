"""Interactive environment. Simulator assets and drop tests (issue 6):

collision   mesh repair, CoACD convex decomposition, hull decimation (MeshError for bad meshes)
physics     priors (mass, friction, restitution → solref) and uniform-density mass properties
export      collision part OBJs, object.urdf, scene.xml (MJCF), a free settle of the scene
background  support geoms (floor plane, tabletop boxes) fitted from the scene surface
droptest    the paper's drop-test protocol; MuJoCo C reference; the construction stage's hook
mjx_batch   every drop test of a bucket in one vmapped, jitted MJX program
cases       procedural shapes and poses with known verdicts (tests, benchmark)
stage       run_physics (the stage) and run_droptest (re-run on an exported folder)
"""
