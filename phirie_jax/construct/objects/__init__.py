"""Object construction: each instance becomes an asset (mesh, pose S_i(0), visual Gaussians).

stage       run_objects: the stage driver
config      ObjectsConfig (with RegistrationConfig)
candidates  the candidate pool: external files and built-in generators
generators  visual hull, extrusion, primitive fits
meshing     occupancy grids → meshes
support     the gravity frame and the plane each instance stands on
register    the batched registration search (kernels.registration) and placement scores
checks      the paper's checks and the lexicographic ranking
assets      mesh.obj and visual.ply of an accepted object
"""
