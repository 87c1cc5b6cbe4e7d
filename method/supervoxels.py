"""VCCS supervoxels (Papon et al., CVPR 2013), following PCL's ``SupervoxelClustering``.

Steps, with PCL's parameter names:

1. Voxelise the cloud at ``voxel_resolution`` (voxel = mean of its points, colours and, when
   given, normals); voxels are adjacent when they are among each other's 26 neighbours. The voxel
   and seed grids are anchored on the cloud (:func:`grid_origin`), not at the world origin: a
   cloud extracted from a TSDF of the same voxel size has most coordinates on one lattice, and a
   grid whose faces pass through that lattice splits surfaces at random (``floor`` of values on a
   face); anchored, the lattice falls on voxel centres and the partition moves with the cloud.
2. Voxel normals: the averaged input normals if given, else the PCA normal of the voxel
   centroids in the voxel's two-ring neighbourhood, flipped towards ``viewpoint`` (PCL: origin).
3. Seeds: one per occupied cell of a ``seed_resolution`` grid (the voxel nearest to the cell
   centre), kept only if more than ``0.05·π·(seed/2)²/voxel²`` voxels lie within ``seed/2``.
4. Flow-constrained expansion over the voxel adjacency for ``int(1.8·seed/voxel) − 1``
   iterations: each supervoxel tries to take every neighbour of its voxels, stealing it when
   ``D = wc·|Δrgb|/255 + ws·|Δxyz|/seed_resolution + wn·(1 − |n_sv·n_v|)`` beats the voxel's
   current distance; supervoxel centroids (mean xyz/rgb, normalised mean normal) are then updated.

Units: metres; points in any frame (normals oriented consistently, e.g. outwards).
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy.spatial import cKDTree

_OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)],
                    dtype=np.int64)
_BITS = 21  # per axis, packed into one int64 key
_BIAS = 1 << (_BITS - 1)


@dataclass
class Supervoxels:
    """Result of :func:`supervoxel_clustering`.

    point_voxel: N int64 voxel of each input point; voxel_label: V int32 supervoxel of each voxel
    (−1 = not reached); point_label: N int32 (−1 = not reached); centroids, normals: S×3;
    colors: S×3 (0–255); voxel_count: S; edges: E×2 int32 supervoxel adjacency (i < j).
    """

    point_voxel: np.ndarray
    voxel_label: np.ndarray
    point_label: np.ndarray
    centroids: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    voxel_count: np.ndarray
    edges: np.ndarray

    @property
    def n(self) -> int:
        return len(self.centroids)


def pack_keys(keys: np.ndarray) -> np.ndarray:
    """Integer voxel keys V×3 → one int64 per voxel (21 bits per axis)."""
    k = keys + _BIAS
    if (k < 0).any() or (k >= (1 << _BITS)).any():
        raise ValueError("point cloud extent too large for the voxel resolution (2^21 voxels per axis)")
    return (k[:, 0] << (2 * _BITS)) | (k[:, 1] << _BITS) | k[:, 2]


def grid_origin(points: np.ndarray, voxel: float) -> np.ndarray:
    """Origin (3, m) of the voxel grid for ``points`` (N×3, m): per axis, the circular mean phase of
    the coordinates modulo ``voxel``, shifted by half a voxel.

    Coordinates sharing a lattice of spacing ``voxel`` (a TSDF surface: two of each point's three
    coordinates on the TSDF's voxel lattice) dominate the circular mean, so they land on voxel
    centres, never on faces. The origin is translation-covariant: shifting the cloud by t shifts it
    by t modulo ``voxel``, so the partition of the points does not change (up to rounding).
    """
    ang = np.asarray(points, np.float64) * (2.0 * np.pi / voxel)
    phase = np.arctan2(np.sin(ang).sum(0), np.cos(ang).sum(0)) / (2.0 * np.pi)  # in (−½, ½] voxels
    return (phase + 0.5) * voxel


def voxel_adjacency(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """26-neighbour adjacency of integer voxel keys (V×3, unique) as CSR (indptr, indices)."""
    packed = pack_keys(keys)
    order = np.argsort(packed)
    sp = packed[order]
    rows, cols = [], []
    for off in _OFFSETS:
        q = pack_keys(keys + off)
        pos = np.searchsorted(sp, q)
        pos[pos >= len(sp)] = 0
        hit = sp[pos] == q
        rows.append(np.nonzero(hit)[0])
        cols.append(order[pos[hit]])
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    o = np.lexsort((cols, rows))
    rows, cols = rows[o], cols[o]
    indptr = np.zeros(len(keys) + 1, np.int64)
    np.add.at(indptr, rows + 1, 1)
    return np.cumsum(indptr), cols.astype(np.int64)


@numba.njit(cache=True)
def _pca_normals(xyz, indptr, indices, viewpoint):
    """Normal of each voxel from the centroids of its two-ring neighbourhood, flipped to the viewpoint."""
    V = xyz.shape[0]
    out = np.zeros((V, 3))
    mark = np.full(V, -1, np.int64)
    buf = np.empty(V, np.int64)
    for v in range(V):
        m = 0
        mark[v] = v
        buf[m] = v
        m += 1
        for a in range(indptr[v], indptr[v + 1]):
            u = indices[a]
            if mark[u] != v:
                mark[u] = v
                buf[m] = u
                m += 1
            for b in range(indptr[u], indptr[u + 1]):
                w = indices[b]
                if mark[w] != v:
                    mark[w] = v
                    buf[m] = w
                    m += 1
        if m < 3:
            continue
        c = np.zeros(3)
        for i in range(m):
            c += xyz[buf[i]]
        c /= m
        C = np.zeros((3, 3))
        for i in range(m):
            d = xyz[buf[i]] - c
            C += np.outer(d, d)
        w_, vec = np.linalg.eigh(C)
        n = vec[:, 0].copy()
        if np.dot(viewpoint - xyz[v], n) < 0:
            n = -n
        out[v] = n
    return out


@numba.njit(cache=True)
def _expand(xyz, nrm, rgb, indptr, indices, seeds, n_iter, wc, ws, wn, seed_res):
    """Flow-constrained supervoxel growth (PCL ``expandSupervoxels``); returns the owner of each voxel."""
    V = xyz.shape[0]
    S = seeds.shape[0]
    owner = np.full(V, -1, np.int64)
    dist = np.full(V, np.inf)
    c_xyz = np.zeros((S, 3))
    c_nrm = np.zeros((S, 3))
    c_rgb = np.zeros((S, 3))
    for s in range(S):
        owner[seeds[s]] = s
        c_xyz[s] = xyz[seeds[s]]
        c_nrm[s] = nrm[seeds[s]]
        c_rgb[s] = rgb[seeds[s]]
    alive = np.ones(S, np.bool_)
    for _ in range(n_iter):
        # voxels of each supervoxel at the start of this iteration (CSR by owner)
        cnt = np.zeros(S + 1, np.int64)
        for v in range(V):
            if owner[v] >= 0:
                cnt[owner[v] + 1] += 1
        start = np.cumsum(cnt)
        fill = start[:-1].copy()
        members = np.empty(start[-1], np.int64)
        for v in range(V):
            if owner[v] >= 0:
                members[fill[owner[v]]] = v
                fill[owner[v]] += 1
        new = np.empty(V, np.int64)
        for s in range(S):
            if not alive[s]:
                continue
            n_new = 0
            for a in range(start[s], start[s + 1]):
                v = members[a]
                if owner[v] != s:  # stolen earlier in this iteration
                    continue
                for b in range(indptr[v], indptr[v + 1]):
                    u = indices[b]
                    if owner[u] == s:
                        continue
                    d = ws * np.sqrt(np.sum((c_xyz[s] - xyz[u]) ** 2)) / seed_res
                    d += wn * (1.0 - abs(np.dot(c_nrm[s], nrm[u])))
                    if wc > 0:
                        d += wc * np.sqrt(np.sum((c_rgb[s] - rgb[u]) ** 2)) / 255.0
                    if d < dist[u]:
                        dist[u] = d
                        owner[u] = -2 - s  # provisional: taken in this iteration, not expanded from yet
                        new[n_new] = u
                        n_new += 1
            for i in range(n_new):
                if owner[new[i]] == -2 - s:
                    owner[new[i]] = s
        # update centroids, drop empty supervoxels
        c_xyz[:] = 0.0
        c_nrm[:] = 0.0
        c_rgb[:] = 0.0
        size = np.zeros(S, np.int64)
        for v in range(V):
            s = owner[v]
            if s >= 0:
                c_xyz[s] += xyz[v]
                c_nrm[s] += nrm[v]
                c_rgb[s] += rgb[v]
                size[s] += 1
        for s in range(S):
            if size[s] == 0:
                alive[s] = False
                continue
            c_xyz[s] /= size[s]
            c_rgb[s] /= size[s]
            nn = np.sqrt(np.sum(c_nrm[s] ** 2))
            if nn > 0:
                c_nrm[s] /= nn
    return owner


def supervoxel_clustering(points: np.ndarray, normals: np.ndarray | None, colors: np.ndarray | None,
                          voxel_resolution: float = 0.0075, seed_resolution: float = 0.03,
                          color_importance: float = 0.0, spatial_importance: float = 1.0,
                          normal_importance: float = 4.0, viewpoint=(0.0, 0.0, 0.0),
                          anchor: str = "cloud") -> Supervoxels:
    """VCCS over-segmentation of an N×3 cloud (m); ``normals`` N×3 oriented, ``colors`` N×3 0–255 or None.

    ``anchor``: "cloud" (grids at :func:`grid_origin`) or "world" (grids at the world origin, the
    former behaviour, kept for the consistency benchmark and its test).
    """
    points = np.asarray(points, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"points must be a non-empty N×3 array, got shape {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("points contain NaN or inf")
    if seed_resolution <= voxel_resolution:
        raise ValueError(f"seed_resolution {seed_resolution} must exceed voxel_resolution {voxel_resolution}")
    if anchor not in ("cloud", "world"):
        raise ValueError(f"anchor must be 'cloud' or 'world', got {anchor!r}")
    origin = grid_origin(points, voxel_resolution) if anchor == "cloud" else np.zeros(3)
    keys_all = np.floor((points - origin) / voxel_resolution).astype(np.int64)
    _, first, point_voxel = np.unique(pack_keys(keys_all), return_index=True, return_inverse=True)
    keys = keys_all[first]
    point_voxel = point_voxel.reshape(-1)
    V = len(keys)
    cnt = np.bincount(point_voxel, minlength=V).astype(np.float64)[:, None]

    def vmean(a):
        out = np.zeros((V, 3))
        np.add.at(out, point_voxel, a)
        return out / cnt

    xyz = vmean(points)
    rgb = vmean(np.asarray(colors, np.float64)) if colors is not None else np.zeros((V, 3))
    indptr, indices = voxel_adjacency(keys)
    if normals is not None:
        nrm = np.zeros((V, 3))
        np.add.at(nrm, point_voxel, np.asarray(normals, np.float64))
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    else:
        nrm = _pca_normals(xyz, indptr, indices, np.asarray(viewpoint, np.float64))

    # seeds: voxel nearest to each occupied seed-grid cell centre, filtered by local voxel density
    tree = cKDTree(xyz)
    # seed grid: faces on voxel faces, anchored modulo the seed size by the same circular mean
    seed_origin = origin if anchor == "world" else \
        origin + voxel_resolution * np.round((grid_origin(points, seed_resolution) - origin) / voxel_resolution)
    cells = np.unique(np.floor((xyz - seed_origin) / seed_resolution).astype(np.int64), axis=0)
    _, seeds = tree.query(seed_origin + (cells + 0.5) * seed_resolution)
    seeds = np.unique(seeds)
    radius = 0.5 * seed_resolution
    min_points = 0.05 * radius * radius * np.pi / (voxel_resolution * voxel_resolution)
    n_near = tree.query_ball_point(xyz[seeds], radius, return_length=True)
    seeds = seeds[n_near > min_points].astype(np.int64)

    n_iter = max(int(1.8 * seed_resolution / voxel_resolution) - 1, 0)
    owner = _expand(xyz, nrm, rgb, indptr, indices, seeds, n_iter, float(color_importance),
                    float(spatial_importance), float(normal_importance), float(seed_resolution))
    used, voxel_label = np.unique(owner, return_inverse=True)
    voxel_label = voxel_label.reshape(-1).astype(np.int32)
    if used[0] < 0:
        voxel_label -= 1
    S = int(voxel_label.max()) + 1
    lab = voxel_label >= 0
    vc = np.bincount(voxel_label[lab], minlength=S).astype(np.float64)

    def smean(a):
        out = np.zeros((S, 3))
        np.add.at(out, voxel_label[lab], a[lab])
        return out

    centroids = smean(xyz) / vc[:, None]
    sv_rgb = smean(rgb) / vc[:, None]
    sv_nrm = smean(nrm)
    sv_nrm /= np.maximum(np.linalg.norm(sv_nrm, axis=1, keepdims=True), 1e-12)

    rows = np.repeat(np.arange(V), np.diff(indptr))
    a, b = voxel_label[rows], voxel_label[indices]
    keep = (a >= 0) & (b >= 0) & (a != b)
    pairs = np.stack([np.minimum(a[keep], b[keep]), np.maximum(a[keep], b[keep])], 1)
    edges = np.unique(pairs, axis=0).astype(np.int32) if len(pairs) else np.zeros((0, 2), np.int32)
    return Supervoxels(point_voxel=point_voxel, voxel_label=voxel_label, point_label=voxel_label[point_voxel],
                       centroids=centroids, normals=sv_nrm, colors=sv_rgb, voxel_count=vc.astype(np.int64),
                       edges=edges)
