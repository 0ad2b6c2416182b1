"""The background branch: G_bg = (G0 \\ ∪R_i) ∪ G_fill.

stage    run_background: the stage driver
config   BackgroundConfig
removal  R_i = R_obs ∪ R_asset ∪ R_mask (occlusion-tested mask votes)
views    crops of camera views and their renderer
targets  inpainting targets: a primary view per object, composited per frame
plane    robust support plane, exposed cells, initial disk Gaussians
refine   the disks refined against the targets (kernels.fill + optax)
"""
