"""Scene Observation: per-view masks → first-hit lifting onto the surface → voxel association.

stage      run_observe: the stage driver
config     ObserveConfig (with SurfaceConfig, AutoMaskConfig)
surface    the scene surface: a scan mesh, or TSDF fusion of rendered depths
floaters   Gaussians left out of the splat-derived surface (haze, blobs, floaters)
masks      mask files, or labels rendered from candidate Gaussians
auto       automatic instance discovery on the splat-derived surface
raycast    first-hit ray casting against a mesh
lift       per-view masks → surface points
associate  voxel association of lifted points across views → instances
evaluate   instances scored against synthetic ground truth
"""
