"""Visual hull: carve a voxel grid with one instance's multi-view masks.

Each view's mask is given as a small state image (uint8, per pixel):
``INSIDE`` (the instance), ``CARVE`` (background: whatever is seen there is not the
instance and nothing in front of it hides it) or ``NO_VOTE`` (another instance, which
may occlude this one, or padding). A voxel centre that projects (in front of the camera,
inside the image) onto a ``CARVE`` pixel gets a carve vote; onto ``INSIDE`` a keep vote.

``view_votes`` handles one view; ``carve`` vmaps it over the views and sums. Views and
image sizes are padded to static shapes by the caller (a padded view is all ``NO_VOTE``).
Pixel centres are at (i + 0.5, j + 0.5) in K's image coordinates (docs/architecture.md "Contracts").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

INSIDE, CARVE, NO_VOTE = 1, 0, 2
MIN_DEPTH = 1e-6  # points this close to (or behind) the camera plane are not seen


def view_votes(centres, K, world_to_camera, state):
    """Votes of one view. centres (V, 3) world; K (3, 3); world_to_camera (4, 4);
    state (H, W) uint8. → keep (V,) int32, carve (V,) int32 (each 0 or 1)."""
    cam = centres @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    z = cam[:, 2]
    front = z > MIN_DEPTH
    safe_z = jnp.where(front, z, 1.0)
    u = (K[0, 0] * cam[:, 0] + K[0, 1] * cam[:, 1]) / safe_z + K[0, 2]
    v = K[1, 1] * cam[:, 1] / safe_z + K[1, 2]
    col, row = jnp.floor(u).astype(jnp.int32), jnp.floor(v).astype(jnp.int32)
    height, width = state.shape
    inside_image = front & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    s = state[jnp.clip(row, 0, height - 1), jnp.clip(col, 0, width - 1)]
    keep = inside_image & (s == INSIDE)
    carve_vote = inside_image & (s == CARVE)
    return keep.astype(jnp.int32), carve_vote.astype(jnp.int32)


def carve(centres, Ks, world_to_cameras, states):
    """Summed votes of every view: (V,) keep counts, (V,) carve counts.

    centres (V, 3) world; Ks (C, 3, 3); world_to_cameras (C, 4, 4); states (C, H, W) uint8.
    """
    keep, carve_votes = jax.vmap(view_votes, in_axes=(None, 0, 0, 0))(centres, Ks, world_to_cameras, states)
    return jnp.sum(keep, axis=0), jnp.sum(carve_votes, axis=0)
