"""Over-segmentation of a reconstructed scene: LCCP fused with SymSeg, then pruning (paper step 2).

Fusion, as in Lu et al.: every symmetric segment from :mod:`selfseg.method.symseg` takes its
points out of the LCCP segments it overlaps (splitting them) and becomes one segment (merging
the LCCP segments inside it), except when LCCP segments inside it have their own symmetry about
the same axis (a bottle standing in a bowl); :func:`fuse_symmetries` gives the exact rule.
Without a detected symmetry the LCCP result is kept. Segments with fewer than
``min_segment_points`` points (or covering less than ``min_segment_area_cm2`` at the cloud's density) are pruned (label −1).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from selfseg.method.lccp import LCCPConfig, lccp_segment, relabel_by_size
from selfseg.method.symseg import (Occupancy, SymSegConfig, Symmetry, axis_close, detect_rotational_symmetries,
                                   outward_fraction)


@dataclass
class OversegConfig:
    lccp: LCCPConfig = field(default_factory=LCCPConfig)
    symseg: SymSegConfig = field(default_factory=SymSegConfig)
    use_symseg: bool = True
    min_segment_points: int = 200  # the paper's pruning: segments with fewer points are dropped ...
    # ... unless this is > 0: then the threshold is this area (cm²) times the cloud's measured density
    # (points per cm², :func:`surface_density_per_cm2`), so it means the same at every voxel size
    min_segment_area_cm2: float = 0.0


def fuse_symmetries(lccp_labels: np.ndarray, points: np.ndarray, normals: np.ndarray, symmetries: list[Symmetry],
                    cfg: SymSegConfig) -> np.ndarray:
    """Apply symmetric segments (largest first) to LCCP labels; returns uncompacted int labels (−1 kept).

    Inside a symmetric segment S, the LCCP segments with their own complete symmetry about S's axis
    ("own", :attr:`Symmetry.own_segments`) decide:

    * none: S becomes one segment (splitting the LCCP segments it overlaps, merging those inside);
    * some, and the rest of S is a sizeable surface around them (median distance to the axis larger
      than theirs) partly facing away from the axis (a bowl around a bottle, even when LCCP cut the
      bowl into wedges): the own segments stay, the rest is one segment;
    * two or more, otherwise (rest small, inside them or facing the axis only: a cup's inside): own
      segments stay and the rest joins them by contact (:func:`_split_among_own`);
    * one, otherwise (e.g. a bowl's outer ring with its inside): S becomes one segment.
    """
    lccp = np.asarray(lccp_labels)
    out = lccp.astype(np.int64).copy()
    next_label = int(out.max(initial=-1)) + 1
    claimed = np.zeros(len(out), bool)
    used_own: set[int] = set()
    for sym in symmetries:
        if sym.own_segments and set(sym.own_segments) <= used_own:
            continue  # this segment's own symmetry was already resolved inside a larger one
        sup = sym.support[~claimed[sym.support]]
        if len(sup) == 0:
            continue
        piece = lccp[sup]
        present = set(np.unique(piece).tolist())
        own = sorted({s for other in symmetries if axis_close(other, sym.axis_point, sym.axis_dir, cfg)
                      for s in other.own_segments if s in present})
        rest = ~np.isin(piece, own)
        radius = _axis_distance(points[sup], sym.axis_point, sym.axis_dir)
        rest_is_object = (bool(own) and rest.sum() >= cfg.min_seed_points
                          and np.median(radius[rest]) > np.median(radius[~rest]) and outward_fraction(
                              points[sup[rest]], normals[sup[rest]], sym.axis_point, sym.axis_dir,
                              cfg.min_radius_m) >= 0.25)
        if rest_is_object:
            used_own |= set(own)
            out[sup[~rest]] = piece[~rest]
            out[sup[rest]] = next_label
            next_label += 1
        elif len(own) >= 2:
            used_own |= set(own)
            out[sup] = _split_among_own(piece, points[sup], own, cfg.neighbor_radius_m)
        else:
            out[sup] = next_label
            next_label += 1
        claimed[sup] = True
    return out


def _axis_distance(points: np.ndarray, c: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Distance (m) of each point (N×3, m) from the axis through ``c`` along the unit vector ``a``."""
    d = points - c
    return np.linalg.norm(d - np.outer(d @ a, a), axis=1)


def _split_among_own(piece: np.ndarray, pts: np.ndarray, own: list[int], radius: float) -> np.ndarray:
    """Labels for the points of a symmetric segment shared by several self-symmetric LCCP segments.

    The self-symmetric segments keep their labels; every other LCCP piece inside the symmetric
    segment joins, greedily, the already-assigned piece it shares most contacts (point pairs closer
    than ``radius``) with; pieces touching none join the largest self-symmetric segment.
    """
    pairs = cKDTree(pts).query_pairs(radius, output_type="ndarray")
    a, b = piece[pairs[:, 0]], piece[pairs[:, 1]]
    cross = a != b
    contact: dict[tuple[int, int], int] = {}
    for x, y in zip(a[cross].tolist(), b[cross].tolist()):
        contact[(x, y)] = contact.get((x, y), 0) + 1
        contact[(y, x)] = contact.get((y, x), 0) + 1
    group = {o: o for o in own}
    pending = set(np.unique(piece).tolist()) - set(own)
    while pending:
        best = max(((contact.get((p, q), 0), -p, p, q) for p in sorted(pending) for q in group), default=None)
        if best is None or best[0] == 0:
            largest = max(own, key=lambda o: (int(np.sum(piece == o)), -o))
            group.update({p: largest for p in pending})
            break
        group[best[2]] = group[best[3]]
        pending.remove(best[2])
    lut = {p: g for p, g in group.items()}
    return np.array([lut[p] for p in piece.tolist()], np.int64)


def surface_density_per_cm2(points: np.ndarray, radius_m: float = 0.01, sample: int = 2000, seed: int = 0) -> float:
    """Points per cm² of surface: the median number of points within ``radius_m`` of a point (at most ``sample``
    points asked, chosen with ``seed``) over the area π r² of a flat disc of that radius."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return 0.0
    query = pts if len(pts) <= sample else pts[np.random.default_rng(seed).choice(len(pts), sample, replace=False)]
    counts = cKDTree(pts).query_ball_point(query, radius_m, return_length=True)
    return float(np.median(counts) / (np.pi * (radius_m * 100.0) ** 2))


def min_points(points: np.ndarray, cfg: OversegConfig) -> int:
    """The pruning threshold in points: ``min_segment_points``, or the area threshold at the cloud's density."""
    if cfg.min_segment_area_cm2 <= 0:
        return cfg.min_segment_points
    return max(1, int(round(cfg.min_segment_area_cm2 * surface_density_per_cm2(points))))


def prune_small(labels: np.ndarray, min_points: int) -> np.ndarray:
    """Labels of segments with fewer than ``min_points`` points set to −1; the rest renumbered 0..S−1 by size."""
    labels = np.asarray(labels)
    ok = labels >= 0
    uniq, inv, cnt = np.unique(labels[ok], return_inverse=True, return_counts=True)
    out = labels.astype(np.int64).copy()
    out[ok] = np.where(cnt[inv.reshape(-1)] >= min_points, labels[ok], -1)
    return relabel_by_size(out)


def oversegment(points: np.ndarray, normals: np.ndarray, colors: np.ndarray | None, occupancy: Occupancy | None,
                cfg: OversegConfig | None = None, return_symmetries: bool = False):
    """Final int32 segment label per point (world m, outward normals), 0..S−1 by size, −1 = pruned.

    With ``return_symmetries`` also returns the detected :class:`Symmetry` list.
    """
    cfg = cfg or OversegConfig()
    labels = lccp_segment(points, normals, colors, cfg.lccp)
    syms: list[Symmetry] = []
    if cfg.use_symseg and normals is not None and (labels >= 0).any():
        syms = detect_rotational_symmetries(points, normals, labels, occupancy, cfg.symseg)
        labels = fuse_symmetries(labels, points, normals, syms, cfg.symseg)
    out = prune_small(labels, min_points(points, cfg))
    return (out, syms) if return_symmetries else out
