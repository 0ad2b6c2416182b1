"""phirie_jax: a captured 3DGS scene → an interactive simulation scene (the φ-RIE method).

The folders follow the pipeline (``pipeline.py`` holds the stage table):

types, geometry, layout   shared records, host geometry helpers, every output file name
io/                       file formats only (3DGS PLY, COLMAP, transforms.json, images, meshes)
observe/                  Scene Observation: masks → lifting → instances
construct/objects/        candidates → registration → checks → selection → assets
construct/physics/        collision, priors, MuJoCo bodies, MJCF/URDF, drop tests
construct/background/     removal → inpainting targets → plane-disk fill
interact/                 runtime: Environment, batched MJX worlds, rollouts
synthetic/                procedural tabletops with ground truth (the embedded default scene)

Pure JAX kernels live in the sibling package ``kernels``.
"""
