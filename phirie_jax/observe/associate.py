"""Voxel association of lifted proposals into instances (the paper's 2 cm, 0.25, ≥ 2 views).

Each proposal becomes a set of voxel keys. Pairwise intersections of all proposals come
from one sparse product of the (proposal × voxel) incidence matrix — hashed keys, no
Python loop over pairs. Proposals of different views are linked when the IoU of their
voxel sets reaches ``overlap`` (and, when the source gives identities, when they carry
the same one); instances are the connected components supported by ≥ ``min_views``
distinct views. Components of one identity are one instance (the mask value is the
identity). Every proposal left out is returned with its reason.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from phirie_jax.observe.lift import Proposal
from phirie_jax.observe.surface import pack_keys


@dataclasses.dataclass(frozen=True)
class Association:
    groups: list[tuple[int, list[int]]]  # (instance id, proposal indices), ids ascending
    rejected: list[dict]                 # {proposal, view, label, instance_id, reason}
    iou: sparse.csr_matrix               # (P, P) voxel IoU of every overlapping pair


def voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """Unique int64 keys of the voxels (edge ``voxel``) that hold the points."""
    return np.unique(pack_keys(np.floor(np.asarray(points) / voxel)))


def voxel_iou(key_sets: list[np.ndarray]) -> sparse.csr_matrix:
    """(P, P) IoU of voxel key sets, non-zero only for pairs that share a voxel."""
    n = len(key_sets)
    if n == 0:
        return sparse.csr_matrix((0, 0))
    rows = np.repeat(np.arange(n), [len(k) for k in key_sets])
    all_keys = np.concatenate(key_sets) if n else np.zeros(0, np.int64)
    _, cols = np.unique(all_keys, return_inverse=True)
    incidence = sparse.csr_matrix((np.ones(len(rows), np.float64), (rows, cols.ravel())),
                                  shape=(n, int(cols.max()) + 1 if len(cols) else 0))
    inter = (incidence @ incidence.T).tocoo()
    sizes = np.asarray([len(k) for k in key_sets], np.float64)
    union = sizes[inter.row] + sizes[inter.col] - inter.data
    return sparse.csr_matrix((inter.data / union, (inter.row, inter.col)), shape=(n, n))


def associate(proposals: list[Proposal], voxel: float, overlap: float, min_views: int) -> Association:
    """Group proposals into instances; see the module docstring."""
    n = len(proposals)
    iou = voxel_iou([voxel_keys(p.points, voxel) for p in proposals])
    views = np.array([p.view for p in proposals], np.int64)
    ids = np.array([-1 if p.instance_id is None else p.instance_id for p in proposals], np.int64)
    coo = iou.tocoo()
    link = ((coo.data >= overlap) & (views[coo.row] != views[coo.col]) & (ids[coo.row] == ids[coo.col]))
    graph = sparse.csr_matrix((np.ones(int(link.sum())), (coo.row[link], coo.col[link])), shape=(n, n))
    _, component = connected_components(graph, directed=False) if n else (0, np.zeros(0, np.int64))

    members: dict[int, list[int]] = {}
    for index, comp in enumerate(component):
        members.setdefault(int(comp), []).append(index)
    kept: dict[int, list[int]] = {}  # identity key → proposal indices
    rejected = []
    for comp, idx in sorted(members.items(), key=lambda kv: kv[1][0]):
        support = len(set(views[idx].tolist()))
        if support < min_views:
            for i in idx:
                p = proposals[i]
                who = f"id {p.instance_id}" if p.instance_id is not None else "any other proposal"
                rejected.append({"proposal": i, "view": p.view, "label": p.label, "instance_id": p.instance_id,
                                 "reason": f"supported by {support} view(s) (< {min_views}): voxel IoU "
                                           f"< {overlap} with every other view of {who}"})
            continue
        key = int(ids[idx[0]]) if ids[idx[0]] >= 0 else -1 - comp  # unlabelled: one per component
        kept.setdefault(key, []).extend(idx)

    labelled = sorted(k for k in kept if k >= 0)
    unlabelled = sorted((k for k in kept if k < 0), key=lambda k: kept[k][0])
    groups = [(k, sorted(kept[k])) for k in labelled]
    next_id = (max(labelled) + 1) if labelled else 1
    for offset, k in enumerate(unlabelled):
        groups.append((next_id + offset, sorted(kept[k])))
    return Association(groups, rejected, iou)
