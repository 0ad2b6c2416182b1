"""The interactive environment (runtime only).

environment  Environment: MuJoCo C moves the bodies, their Gaussians follow, one rasterization
batched      BatchedEnvironment: many MJX (or MuJoCo Warp) worlds stepped and rendered in one call
mjx_model    the batched worlds' collision model (one convex hull per object)
rollout      shoot-and-render rollouts written to MP4
"""
