"""Voxel association: one object in many views merges, touching objects stay apart,
unsupported proposals are recorded; the sparse IoU against a set-based brute force."""

from __future__ import annotations

import numpy as np
import trimesh

from phirie_jax.observe.associate import associate, voxel_iou, voxel_keys
from phirie_jax.observe.config import ObserveConfig
from phirie_jax.observe.lift import Proposal, lift_view
from phirie_jax.observe.masks import Segment, ViewMasks
from phirie_jax.observe.raycast import Raycaster
from tests.observe.helpers import id_masks, ring

CONFIG = ObserveConfig()


def table(z=0.0):
    slab = trimesh.creation.box(extents=[2.0, 2.0, 0.02])
    slab.apply_translation([0, 0, z - 0.01])
    return slab


def proposals_from_views(objects: dict[int, trimesh.Trimesh], cameras, identity: bool) -> list[Proposal]:
    """Lift per-view masks projected from the meshes; ``identity=False`` hides the ids
    (labels permuted per view, like an external segmenter)."""
    background = table()
    masks = id_masks(objects, background, cameras)
    scene = trimesh.util.concatenate([background, *objects.values()])
    caster = Raycaster(scene.vertices, scene.faces)
    out = []
    rng = np.random.default_rng(0)
    for view, (cam, mask) in enumerate(zip(cameras, masks)):
        labels = mask.astype(np.int64)
        if not identity:  # per-view labels with no meaning across views
            perm = np.concatenate([[0], rng.permutation(np.arange(1, labels.max() + 1)) + 10])
            labels = perm[labels]
        segments = {int(k): Segment(int(k), int(k) if identity else None) for k in np.unique(labels) if k}
        found, _ = lift_view(caster, cam, ViewMasks(view, labels, segments), CONFIG)
        out += found
    return out


def box_at(x, y, size=(0.12, 0.12, 0.15)):
    box = trimesh.creation.box(extents=size)
    box.apply_translation([x, y, size[2] / 2])
    return box


def test_one_object_seen_in_several_views_is_one_instance():
    cams = ring(6, 0.8, 0.6, target=(0, 0, 0.05), width=160, height_px=120, focal=300.0)
    proposals = proposals_from_views({1: box_at(0.02, -0.01)}, cams, identity=False)
    assert len(proposals) == 6 and all(p.instance_id is None for p in proposals)
    result = associate(proposals, CONFIG.voxel, CONFIG.overlap, CONFIG.min_views)
    assert len(result.groups) == 1 and result.rejected == []
    assert sorted(proposals[i].view for i in result.groups[0][1]) == list(range(6))


def test_two_touching_objects_stay_apart():
    # two boxes sharing a face: their masks touch in every view
    objects = {1: box_at(-0.049, 0.007), 2: box_at(0.071, 0.007)}  # contact at x = 0.011, inside a voxel
    cams = ring(8, 0.8, 0.7, target=(0, 0, 0.05), width=160, height_px=120, focal=220.0)
    proposals = proposals_from_views(objects, cams, identity=False)
    truth = []
    for p in proposals:  # which box each proposal really is: the one its points are on
        x = np.median(p.points[:, 0])
        truth.append(1 if x < 0.011 else 2)
    result = associate(proposals, CONFIG.voxel, CONFIG.overlap, CONFIG.min_views)
    assert len(result.groups) == 2
    for _, members in result.groups:
        assert len({truth[i] for i in members}) == 1  # never mixed
    assert sum(len(m) for _, m in result.groups) + len(result.rejected) == len(proposals)
    # with ids (mask files) the same boxes are the same two instances, named by their ids
    labelled = proposals_from_views(objects, cams, identity=True)
    result = associate(labelled, CONFIG.voxel, CONFIG.overlap, CONFIG.min_views)
    assert [k for k, _ in result.groups] == [1, 2]
    for k, members in result.groups:
        assert all(labelled[i].instance_id == k for i in members)


def _proposal(view, points, instance_id=None):
    return Proposal(view, 1, instance_id, None, None, np.asarray(points, float), len(points), (0, 0, 1, 1))


def test_single_view_and_mismatched_proposals_are_rejected_with_reasons():
    rng = np.random.default_rng(2)
    blob = rng.uniform(0, 0.1, size=(200, 3))
    far = blob + 5.0
    proposals = [_proposal(0, blob), _proposal(1, blob + 0.003), _proposal(2, far), _proposal(2, blob)]
    result = associate(proposals, 0.02, 0.25, 2)
    assert result.groups == [(1, [0, 1, 3])]
    (rej,) = result.rejected
    assert rej["proposal"] == 2 and "supported by 1 view(s) (< 2)" in rej["reason"]
    # the same view twice is not two views of support
    result = associate([_proposal(0, blob), _proposal(0, blob + 0.001)], 0.02, 0.25, 2)
    assert result.groups == [] and len(result.rejected) == 2


def test_identities_never_link_and_one_identity_is_one_instance():
    rng = np.random.default_rng(3)
    blob = rng.uniform(0, 0.1, size=(200, 3))
    other = blob + np.array([2.0, 0, 0])
    proposals = [_proposal(0, blob, 4), _proposal(1, blob, 4), _proposal(1, blob, 9), _proposal(2, blob, 9),
                 _proposal(3, other, 4), _proposal(4, other, 4)]
    result = associate(proposals, 0.02, 0.25, 2)
    # id 4 seen as two separate components (both multi-view) is still one instance
    assert result.groups == [(4, [0, 1, 4, 5]), (9, [2, 3])] and result.rejected == []


def test_voxel_iou_matches_set_arithmetic():
    rng = np.random.default_rng(4)
    sets = [rng.uniform(0, 0.2, size=(rng.integers(5, 80), 3)) + rng.uniform(0, 0.1) for _ in range(7)]
    fast = voxel_iou([voxel_keys(s, 0.02) for s in sets]).toarray()
    for i, a in enumerate(sets):
        for j, b in enumerate(sets):
            va = {tuple(v) for v in np.floor(a / 0.02).astype(int)}
            vb = {tuple(v) for v in np.floor(b / 0.02).astype(int)}
            assert np.isclose(fast[i, j], len(va & vb) / len(va | vb))
