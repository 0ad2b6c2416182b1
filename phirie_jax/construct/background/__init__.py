"""The background branch: G_bg = (G0 \\ ∪R_i) ∪ G_fill.

Modules, in the order the stage runs them:

stage    run_background: the stage driver (load → removal → plane and fill → targets → refine → write)
config   BackgroundConfig and its step configs (removal, crops, plane, fill, targets, refine)
removal  R_i = R_obs ∪ R_asset ∪ R_mask (occlusion-tested mask votes)
views    crops of camera views and their renderer
plane    robust support plane, exposed cells, initial disk Gaussians
targets  inpainting targets: a primary view per object, composited per frame
refine   the disks refined against the targets (kernels.fill + optax)
"""
