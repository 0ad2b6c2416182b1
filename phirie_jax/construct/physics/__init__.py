"""Simulator assets and drop tests.

stage       run_physics (the stage) and run_droptest (re-run on an exported folder), as named steps
config      PhysicsConfig (with DropTestConfig); measurements: experiments/results/physics_notes.md
collision   mesh repair, CoACD convex decomposition, hull fallback (MeshError for bad meshes)
parts       the collision part OBJ files (objects/<id>/collision/part_NN.obj), written and read
priors      physics priors (mass, friction, restitution → solref) and mass properties
body        ObjectBody (an object's rigid body), body_name, add_body: the one MuJoCo body builder
supports    support geoms (floor plane, tabletop boxes) fitted from the scene surface
mjcf        scene.xml: the scene as one MjSpec, written to text; a free settle of the scene
urdf        objects/<id>/object.urdf from an ObjectBody
droptest    the paper's drop-test protocol; MuJoCo C reference
settling    the object stage's settling check (candidate_settler), handed to it by the pipeline
mjx_batch   every drop test of a bucket in one vmapped, jitted MJX program
"""
