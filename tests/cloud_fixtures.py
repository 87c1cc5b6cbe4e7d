"""Fused-looking point clouds of analytic meshes for the over-segmentation tests.

Ray-casts the meshes (on a table, top at z = 0) from cameras all around, back-projects the depth
with ≈1 mm noise, keeps one point per ``grid_m`` cell (like a TSDF surface at that voxel size) and
drops the table (z < ``table_cut_m``). Only visible surfaces appear, as in a real reconstruction.
"""
from __future__ import annotations

import numpy as np

from analytic import box
from selfseg.raycast import RaycastScene, backproject, look_at

TABLE_ID = 999


def fused_cloud(meshes, n_views=16, grid_m=0.004, noise_m=0.001, table_cut_m=0.004, seed=0,
                radius=0.5, heights=(0.25, 0.5), width=240, height=180, fx=220.0):
    """(points N×3 m, outward normals N×3, mesh index N (0-based)) of the visible object surfaces."""
    rng = np.random.default_rng(seed)
    table = box((1.0, 1.0, 0.02), (0, 0, -0.01))
    scene = RaycastScene.from_meshes(list(meshes) + [table], ids=list(range(1, len(meshes) + 1)) + [TABLE_ID])
    K = np.array([[fx, 0, width / 2 - 0.5], [0, fx, height / 2 - 0.5], [0, 0, 1.0]])
    target = np.mean([m.bounds.mean(0) for m in meshes], axis=0)
    P, N, L = [], [], []
    for h in heights:
        for a in np.linspace(0, 2 * np.pi, n_views, endpoint=False) + h:
            T = look_at([target[0] + radius * np.cos(a), target[1] + radius * np.sin(a), h], target)
            depth, inst, nrm = scene.render(K, T, width, height)
            depth = np.where(depth > 0, depth + rng.normal(0, noise_m, depth.shape), 0).astype(np.float32)
            pts, vu = backproject(depth, K, (inst > 0) & (inst != TABLE_ID))
            P.append(pts @ T[:3, :3].T + T[:3, 3])
            N.append(nrm[vu[:, 0], vu[:, 1]] @ T[:3, :3].T)
            L.append(inst[vu[:, 0], vu[:, 1]].astype(np.int64) - 1)
    P, N, L = np.concatenate(P), np.concatenate(N), np.concatenate(L)
    _, first = np.unique(np.floor(P / grid_m).astype(np.int64), axis=0, return_index=True)
    P, N, L = P[first], N[first], L[first]
    keep = P[:, 2] > table_cut_m
    return P[keep], N[keep], L[keep]
