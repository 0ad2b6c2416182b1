"""``phirie capture``: from photos or a video to a scene folder (a front stage, outside the pipeline).

frames (pictures, sharp video frames) → sfm (pycolmap: SIFT, matching, incremental mapping,
undistortion to pinhole) → train (3DGS with the project's renderer, ``kernels.splat_fit``) →
an ordinary nerfstudio-layout scene folder that ``phirie convert`` reads. The pipeline never
imports this package.
"""
