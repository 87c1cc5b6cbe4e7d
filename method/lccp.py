"""LCCP: Locally Convex Connected Patches (Stein et al., CVPR 2014), following PCL's ``LCCPSegmentation``.

On the VCCS supervoxel adjacency graph (:mod:`selfseg.method.supervoxels`) each edge between
supervoxels s and t (centroids x, normals n, d = x_s − x_t) is valid when

* convexity: angle(d, n_s) − angle(d, n_t) ≤ 0 (convex), or the normals differ by less than
  ``concavity_tolerance_deg`` (a tolerated concavity);
* sanity (optional): a concave-or-convex call needs the patches to really meet: with
  β = angle(n_s × n_t, d) folded to [0°, 90°], β ≥ 60°/(1 + exp(−0.25·(angle(n_s, n_t) − 25°)));
* smoothness: the step min(|d·n_s|, |d·n_t|) ≤ |n_s × n_t|·seed + smoothness_threshold·voxel;
* extended convexity k: a valid edge also needs ≥ k common neighbours joined to both ends by
  valid edges.

Segments are the connected components of valid edges; segments with fewer than
``min_segment_size`` supervoxels are merged into their largest neighbouring segment.
Defaults are PCL's example program's, except the voxel and seed sizes and the sanity criterion
(on); see ``LCCPConfig``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from selfseg.method.supervoxels import Supervoxels, supervoxel_clustering


@dataclass
class LCCPConfig:
    """VCCS + LCCP parameters (PCL names; lengths in metres, angles in degrees)."""

    # [selfseg] 5 mm / 2.5 cm (PCL's example: 7.5 mm / 3 cm): the VCCS voxel equals the 5 mm TSDF voxel
    # (ReconConfig.voxel_size_m) whose edge zero-crossings make up the fused cloud; a 7.5 mm grid aliases
    # with that lattice (1 or 2 layers per voxel) and joins touching objects (tiny preset: 1.4 of 4
    # objects per video merged, LCCP point precision .73; with these defaults 0 merged, precision .96)
    voxel_resolution_m: float = 0.005
    seed_resolution_m: float = 0.025
    color_importance: float = 0.0
    spatial_importance: float = 1.0
    normal_importance: float = 4.0
    concavity_tolerance_deg: float = 10.0
    smoothness_threshold: float = 0.1
    use_smoothness_check: bool = True
    # [selfseg] on (PCL's example: off): it stops diagonal contacts between faces joining objects;
    # bench/bench_overseg.py recovers 8 of 9 objects with it, 5 without
    use_sanity_criterion: bool = True
    k_factor: int = 0  # extended convexity (PCL example: 1 with -ec, else 0)
    min_segment_size: int = 0  # in supervoxels; smaller segments merge into their largest neighbour


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise angle between vectors, degrees in [0, 180]; 90 if either is zero (as PCL's getAngle3D)."""
    ang = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1)))
    zero = (np.linalg.norm(a, axis=1) < 1e-12) | (np.linalg.norm(b, axis=1) < 1e-12)
    return np.where(zero, 90.0, ang)


def edge_validity(sv: Supervoxels, cfg: LCCPConfig) -> np.ndarray:
    """Bool per supervoxel edge: convex (or tolerated concave), smooth and sane (PCL ``connIsConvex``)."""
    s, t = sv.edges[:, 0], sv.edges[:, 1]
    ns, nt = sv.normals[s], sv.normals[t]
    d = sv.centroids[s] - sv.centroids[t]
    normal_angle = _angle(ns, nt)
    ncross = np.cross(ns, nt)
    convex = (_angle(d, ns) - _angle(d, nt)) <= 0
    valid = convex | (normal_angle < cfg.concavity_tolerance_deg)
    if cfg.use_sanity_criterion:
        beta = _angle(ncross, d)
        beta = np.minimum(beta, 180.0 - beta)
        valid &= ~(beta < 60.0 / (1.0 + np.exp(-0.25 * (normal_angle - 25.0))))
    if cfg.use_smoothness_check:
        step = np.minimum(np.abs(np.sum(d * ns, 1)), np.abs(np.sum(d * nt, 1)))
        expected = np.linalg.norm(ncross, axis=1) * cfg.seed_resolution_m
        valid &= step <= expected + cfg.smoothness_threshold * cfg.voxel_resolution_m
    if cfg.k_factor > 0:
        nbrs: list[set[int]] = [set() for _ in range(sv.n)]
        for (a, b), ok in zip(sv.edges.tolist(), valid.tolist()):
            if ok:
                nbrs[a].add(b)
                nbrs[b].add(a)
        valid = np.array([ok and len(nbrs[a] & nbrs[b]) >= cfg.k_factor
                          for (a, b), ok in zip(sv.edges.tolist(), valid.tolist())], dtype=bool)
    return valid


def _merge_small(seg: np.ndarray, sv_edges: np.ndarray, min_size: int) -> np.ndarray:
    """Merge segments (labels per supervoxel) with < min_size supervoxels into their largest neighbour."""
    seg = seg.copy()
    while True:
        sizes = np.bincount(seg)
        a, b = seg[sv_edges[:, 0]], seg[sv_edges[:, 1]]
        cross = a != b
        nb: dict[int, set[int]] = {}
        for x, y in zip(a[cross].tolist(), b[cross].tolist()):
            nb.setdefault(x, set()).add(y)
            nb.setdefault(y, set()).add(x)
        small = [int(g) for g in np.nonzero((sizes > 0) & (sizes < min_size))[0] if g in nb]
        if not small:
            return seg
        g = min(small, key=lambda x: (sizes[x], x))  # smallest first, deterministic
        target = max(nb[g], key=lambda x: (sizes[x], -x))
        seg[seg == g] = target


def relabel_by_size(labels: np.ndarray) -> np.ndarray:
    """Renumber labels ≥ 0 to 0..S−1 by decreasing count (ties: lower old label first); −1 stays."""
    labels = np.asarray(labels)
    out = np.full(labels.shape, -1, np.int32)
    ok = labels >= 0
    if not ok.any():
        return out
    uniq, inv, cnt = np.unique(labels[ok], return_inverse=True, return_counts=True)
    order = np.lexsort((uniq, -cnt))
    rank = np.empty(len(uniq), np.int32)
    rank[order] = np.arange(len(uniq), dtype=np.int32)
    out[ok] = rank[inv.reshape(-1)]
    return out


def lccp_from_supervoxels(sv: Supervoxels, cfg: LCCPConfig) -> np.ndarray:
    """Segment label per supervoxel (int, not yet compacted) from valid-edge region growing + small-segment merging."""
    if sv.n == 0:
        return np.zeros(0, np.int64)
    valid = edge_validity(sv, cfg)
    e = sv.edges[valid]
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(sv.n, sv.n))
    _, seg = connected_components(graph, directed=False)
    if cfg.min_segment_size > 0:
        seg = _merge_small(seg, sv.edges, cfg.min_segment_size)
    return seg


def run_supervoxels(points: np.ndarray, normals: np.ndarray | None, colors: np.ndarray | None, cfg: LCCPConfig,
                    viewpoint=(0.0, 0.0, 0.0)) -> Supervoxels:
    """VCCS with the supervoxel part of an LCCP config."""
    return supervoxel_clustering(points, normals, colors, cfg.voxel_resolution_m, cfg.seed_resolution_m,
                                 cfg.color_importance, cfg.spatial_importance, cfg.normal_importance, viewpoint)


def lccp_segment(points: np.ndarray, normals: np.ndarray | None, colors: np.ndarray | None, cfg: LCCPConfig,
                 viewpoint=(0.0, 0.0, 0.0)) -> np.ndarray:
    """LCCP over-segmentation of an N×3 cloud (m): int32 label per point, 0..S−1 by size, −1 = unlabelled.

    ``normals`` N×3 (oriented, e.g. outwards) or None to estimate them per voxel, flipped towards
    ``viewpoint`` (the camera centre for a single frame in camera coordinates); ``colors`` N×3 0–255 or None.
    """
    sv = run_supervoxels(points, normals, colors, cfg, viewpoint)
    seg = lccp_from_supervoxels(sv, cfg)
    lab = np.where(sv.point_label >= 0, seg[np.maximum(sv.point_label, 0)], -1)
    return relabel_by_size(lab)
