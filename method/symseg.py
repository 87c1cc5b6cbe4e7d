"""SymSeg-style rotational symmetry detection and symmetric segments (after Ecins et al., ICRA 2018).

Only rotational symmetry is used. For a surface of revolution about the axis (c, a), every
surface normal lies in the plane spanned by the axis and the point's radial direction r, so the
per-point error is e = asin|n · (a × r̂)|.

1. Candidates: for each over-segmentation segment (and each segment joined with its
   neighbours) with enough points, the best-fitting of the three PCA axes through its centroid
   is refined by ``scipy.optimize.least_squares`` (robust soft-L1 loss on sin e) and scored:
   symmetry fit (median e over the points whose normal is not parallel to the axis, the only
   ones that carry evidence), perpendicularity (the share of such points), angular coverage
   (share of 10° sectors around the axis that hold points) and occlusion (share of the points,
   moved ``occlusion_inset_m`` inwards and rotated about the axis, that land in observed free
   space of the TSDF; skipped without an occupancy function).
2. Support: a binary graph cut (``scipy.sparse.csgraph.maximum_flow``) over the points near the
   axis (within the seed's radial and axial extent plus a margin), pooled into ``cut_voxel_m``
   voxels: unary cost min(e / inlier, 2) per point for "symmetric" against 1 for "not", Potts
   smoothness between 26-neighbour voxels. Near-duplicate symmetries (similar axis, overlapping
   support) are merged.

Units: metres and degrees; points and normals in the world frame, normals oriented consistently.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import breadth_first_order, maximum_flow

from selfseg.method.lccp import LCCPConfig, lccp_segment
from selfseg.method.segment_graph import build_segment_graph
from selfseg.method.supervoxels import voxel_adjacency

Occupancy = Callable[[np.ndarray], np.ndarray]  # world points N×3 → int8 N: −1 free, 0 unknown, 1 surface/behind


@dataclass
class SymSegConfig:
    """Rotational-symmetry detection and graph-cut parameters (metres, degrees)."""

    min_seed_points: int = 150
    max_fit_points: int = 600  # subsample of a seed used in the least-squares fit
    max_fit_error_deg: float = 8.0  # median normal error of the seed about the axis
    min_perpendicular: float = 0.3  # share of seed normals more than 20° from the axis direction
    min_coverage: float = 0.5  # share of 10° sectors around the axis occupied by seed points
    own_min_coverage: float = 0.9  # a single segment "has its own symmetry" (fusion) from this coverage
    max_occlusion: float = 0.1  # share of rotated seed points that fall in observed free space
    n_rotations: int = 12
    occlusion_inset_m: float = 0.004  # rotated points are moved this far inwards (TSDF sign noise; < thin walls)
    min_radius_m: float = 0.005  # points closer to the axis carry no direction and are ignored
    inlier_deg: float = 10.0  # graph cut: normal error at which "symmetric" and "not" cost the same
    smoothness: float = 0.25  # graph cut: Potts weight between neighbour voxels, per point
    cut_voxel_m: float = 0.005  # graph-cut node size
    neighbor_radius_m: float = 0.008  # segments closer than this are neighbours (seed groups)
    margin_m: float = 0.01  # support region: seed's radial / axial extent plus this margin
    axis_merge_deg: float = 10.0
    axis_merge_dist_m: float = 0.015
    seed: int = 0


@dataclass
class Symmetry:
    """A rotational symmetry: axis through ``axis_point`` along unit ``axis_dir`` (world m), its scores and support."""

    axis_point: np.ndarray
    axis_dir: np.ndarray
    fit_error_deg: float
    perpendicular: float
    coverage: float
    occlusion: float
    seed_segments: list[int]
    own_segments: list[int]  # single seed segments fitted to this axis with coverage ≥ own_min_coverage
    support: np.ndarray = field(repr=False)  # point indices of the symmetric segment


def normal_errors(points: np.ndarray, normals: np.ndarray, c: np.ndarray,
                  a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sin of each normal's angle to its axis plane, radial distance to the axis in m)."""
    d = points - c
    r = d - np.outer(d @ a, a)
    rad = np.linalg.norm(r, axis=1)
    t = np.cross(a, r) / np.maximum(rad, 1e-12)[:, None]
    return np.abs(np.sum(normals * t, axis=1)), rad


def _unit(theta_phi: np.ndarray) -> np.ndarray:
    th, ph = theta_phi
    return np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])


def _fit_axis(p: np.ndarray, n: np.ndarray, c0: np.ndarray, a0: np.ndarray, min_r: float):
    """Least-squares refinement of an axis (point, direction) from an initial guess."""
    e1 = np.cross(a0, [1.0, 0, 0] if abs(a0[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a0, e1)
    x0 = np.array([np.arccos(np.clip(a0[2], -1, 1)), np.arctan2(a0[1], a0[0]), 0.0, 0.0])

    def res(x):
        a = _unit(x[:2])
        c = c0 + x[2] * e1 + x[3] * e2
        err, rad = normal_errors(p, n, c, a)
        return np.where(rad > min_r, err, 0.0)

    sol = least_squares(res, x0, loss="soft_l1", f_scale=np.sin(np.radians(5.0)), max_nfev=60)
    a = _unit(sol.x[:2])
    c = c0 + sol.x[2] * e1 + sol.x[3] * e2
    c = c + a * ((p.mean(0) - c) @ a)  # axis point level with the seed centroid
    return c, a


def _scores(p, n, c, a, occupancy, cfg: SymSegConfig):
    err, rad = normal_errors(p, n, c, a)
    use = rad > cfg.min_radius_m
    informative = use & (np.abs(n @ a) < np.cos(np.radians(20.0)))  # normals parallel to the axis fit any axis
    if informative.sum() < 10:
        return None
    fit = float(np.degrees(np.arcsin(np.clip(np.median(err[informative]), 0, 1))))
    perp = float(informative.sum() / use.sum())
    e1 = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    d = p[informative] - c
    ang = np.arctan2(d @ e2, d @ e1)
    coverage = len(np.unique(np.floor((ang + np.pi) / np.radians(10.0)).astype(int) % 36)) / 36.0
    occl = 0.0
    if occupancy is not None:
        rot_pts = []
        q = p - cfg.occlusion_inset_m * n  # just behind the surface: a true symmetry lands inside the object
        for k in range(1, cfg.n_rotations):
            th = 2 * np.pi * k / cfg.n_rotations
            v = q - c  # Rodrigues rotation about the axis
            vr = v * np.cos(th) + np.cross(a, v) * np.sin(th) + np.outer(v @ a, a) * (1 - np.cos(th))
            rot_pts.append(c + vr)
        occ = np.asarray(occupancy(np.concatenate(rot_pts)))
        occl = float(np.mean(occ == -1))
    return fit, perp, coverage, occl


def _graph_cut_support(points, normals, c, a, seed_idx, cfg: SymSegConfig) -> np.ndarray:
    """Point indices labelled symmetric by a min cut over the voxels near the seed's extent.

    Nodes are ``cut_voxel_m`` voxels of the region's points (unary: the sum of their points'
    costs), with Potts edges of weight smoothness·(mean point count) between 26-neighbour voxels.
    """
    d = points - c
    h = d @ a
    rad = np.linalg.norm(d - np.outer(h, a), axis=1)
    hs, rs = h[seed_idx], rad[seed_idx]
    region = np.nonzero((rad <= rs.max() + cfg.margin_m) & (h >= hs.min() - cfg.margin_m)
                        & (h <= hs.max() + cfg.margin_m))[0]
    err, rr = normal_errors(points[region], normals[region], c, a)
    ang = np.degrees(np.arcsin(np.clip(err, 0, 1)))
    cost_sym = np.where(rr > cfg.min_radius_m, np.minimum(ang / cfg.inlier_deg, 2.0), 0.0)
    keys, vox = np.unique(np.floor(points[region] / cfg.cut_voxel_m).astype(np.int64), axis=0, return_inverse=True)
    vox = vox.reshape(-1)
    m = len(keys)
    count = np.bincount(vox, minlength=m).astype(np.float64)
    unary = np.bincount(vox, weights=1.0 - cost_sym, minlength=m)  # > 0: prefers "symmetric"
    indptr, nb = voxel_adjacency(keys)
    rows = np.repeat(np.arange(m), np.diff(indptr))
    scale = 100.0
    src, snk = m, m + 1
    w = np.round(cfg.smoothness * 0.5 * (count[rows] + count[nb]) * scale).astype(np.int64)
    cap_s = np.round(np.maximum(unary, 0) * scale).astype(np.int64)  # paid if the voxel is "not symmetric"
    cap_t = np.round(np.maximum(-unary, 0) * scale).astype(np.int64)  # paid if it is "symmetric"
    all_r = np.concatenate([np.full(m, src), np.arange(m), rows])
    all_c = np.concatenate([np.arange(m), np.full(m, snk), nb])
    caps = np.concatenate([cap_s, cap_t, w])
    keep = caps > 0
    if caps.max(initial=0) >= 2**31:
        raise ValueError("graph-cut capacities overflow int32; lower SymSegConfig.smoothness or cut_voxel_m")
    cap = csr_matrix(coo_matrix((caps[keep].astype(np.int32), (all_r[keep], all_c[keep])), shape=(m + 2, m + 2)))
    flow = maximum_flow(cap, src, snk).flow
    resid = (cap - flow).tocsr()
    resid.data[resid.data < 0] = 0
    resid.eliminate_zeros()
    reach = breadth_first_order(resid, src, directed=True, return_predecessors=False)
    sym_vox = np.zeros(m, bool)
    sym_vox[reach[reach < m]] = True
    return np.sort(region[sym_vox[vox]])


def outward_fraction(points: np.ndarray, normals: np.ndarray, c: np.ndarray, a: np.ndarray, min_r: float) -> float:
    """Share of the points (farther than ``min_r`` from the axis) whose normal points away from the axis."""
    d = points - c
    r = d - np.outer(d @ a, a)
    use = np.linalg.norm(r, axis=1) > min_r
    return float(np.mean(np.sum(normals[use] * r[use], axis=1) > 0)) if use.any() else 0.0


def axis_close(s1: Symmetry, c: np.ndarray, a: np.ndarray, cfg: SymSegConfig) -> bool:
    """Whether the axis (c, a) is within cfg.axis_merge_deg and cfg.axis_merge_dist_m of s1's axis."""
    if np.degrees(np.arccos(min(abs(float(s1.axis_dir @ a)), 1.0))) > cfg.axis_merge_deg:
        return False
    d = c - s1.axis_point
    return float(np.linalg.norm(d - (d @ s1.axis_dir) * s1.axis_dir)) <= cfg.axis_merge_dist_m


def _seed_groups(points, segments, cfg: SymSegConfig) -> list[list[int]]:
    """Seed segment-id lists: each big segment alone, and each big segment with its 3D neighbours."""
    ok = segments >= 0
    uniq = np.unique(segments[ok])
    compact = np.full(segments.shape, -1, np.int32)
    compact[ok] = np.searchsorted(uniq, segments[ok])
    g = build_segment_graph(points, compact, cfg.neighbor_radius_m)
    groups = [[int(s)] for s in range(len(uniq)) if g.sizes[s] >= cfg.min_seed_points]
    nb: dict[int, set[int]] = {}
    for i, j in g.edges.tolist():
        nb.setdefault(i, set()).add(j)
        nb.setdefault(j, set()).add(i)
    for s in range(len(uniq)):
        if s in nb and g.sizes[s] >= cfg.min_seed_points:
            groups.append(sorted({s} | nb[s]))
    seen, out = set(), []
    for grp in groups:
        if tuple(grp) not in seen:
            seen.add(tuple(grp))
            out.append([int(uniq[s]) for s in grp])
    return out


def detect_rotational_symmetries(points: np.ndarray, normals: np.ndarray, segments: np.ndarray,
                                 occupancy: Occupancy | None = None,
                                 cfg: SymSegConfig | None = None) -> list[Symmetry]:
    """Accepted rotational symmetries with their graph-cut support, largest support first.

    ``segments``: N int labels of an over-segmentation (−1 = none) whose segments seed the axes.
    Each returned symmetry lists the seed segment ids it was fitted to (merged duplicates included).
    """
    cfg = cfg or SymSegConfig()
    points = np.asarray(points, np.float64)
    normals = np.asarray(normals, np.float64)
    segments = np.asarray(segments)
    rng = np.random.default_rng(cfg.seed)
    found: list[Symmetry] = []
    for grp in _seed_groups(points, segments, cfg):
        idx = np.nonzero(np.isin(segments, grp))[0]
        sub = idx if len(idx) <= cfg.max_fit_points else np.sort(rng.choice(idx, cfg.max_fit_points, replace=False))
        p, n = points[sub], normals[sub]
        c0 = p.mean(0)
        _, vecs = np.linalg.eigh(np.cov((p - c0).T))
        # refine only the PCA axis whose initial symmetry fit is best
        initial = [(sc[0], k) for k in range(3) if (sc := _scores(p, n, c0, vecs[:, k], None, cfg)) is not None]
        if not initial:
            continue
        c, a = _fit_axis(p, n, c0, vecs[:, min(initial)[1]], cfg.min_radius_m)
        sc = _scores(p, n, c, a, None, cfg)
        if sc is None:
            continue
        fit, perp, cov, _ = sc
        if fit > cfg.max_fit_error_deg or perp < cfg.min_perpendicular or cov < cfg.min_coverage:
            continue
        occl = _scores(p, n, c, a, occupancy, cfg)[3] if occupancy is not None else 0.0
        if occl > cfg.max_occlusion:
            continue
        # a single segment has its "own" symmetry only if it is a whole surface of revolution by
        # itself (a bottle in a bowl), not a wedge of a larger one (a piece of the bowl)
        own = len(grp) == 1 and cov >= cfg.own_min_coverage
        dup = next((s for s in found if axis_close(s, c, a, cfg)), None)
        if dup is not None and np.isin(idx, dup.support).mean() > 0.5:
            dup.seed_segments = sorted(set(dup.seed_segments) | set(grp))
            if own and grp[0] not in dup.own_segments:
                dup.own_segments.append(grp[0])
            continue
        support = _graph_cut_support(points, normals, c, a, idx, cfg)
        if len(support) < cfg.min_seed_points:
            continue
        found.append(Symmetry(c, a, fit, perp, cov, occl, list(grp), list(grp) if own else [], support))
    return sorted(found, key=lambda s: -len(s.support))


def symseg_segment(points: np.ndarray, normals: np.ndarray, occupancy: Occupancy | None,
                   cfg: SymSegConfig | None = None, segments: np.ndarray | None = None) -> np.ndarray:
    """int32 label per point of its symmetric segment (largest symmetry first), −1 = none.

    ``segments`` seeds the candidate axes; None runs LCCP with its default config first.
    """
    if segments is None:
        segments = lccp_segment(points, normals, None, LCCPConfig())
    out = np.full(len(points), -1, np.int32)
    for k, s in enumerate(detect_rotational_symmetries(points, normals, segments, occupancy, cfg)):
        free = s.support[out[s.support] < 0]
        out[free] = k
    return out
