"""Z-buffer projection of world points into a camera: per-frame label maps and foreground masks.

Units: metres. ``K`` is 3×3 in the OpenCV pixel-centre convention (pixel (u, v) covers
[u − 0.5, u + 0.5) × [v − 0.5, v + 0.5) and its centre has integer coordinates), as in
:mod:`selfseg.dataset`. ``T_world_cam`` maps camera-frame points (x right, y down, z forward)
into the world frame.

Each point is splatted as a (2·splat_px + 1)² square of pixels (a z-buffer, see :func:`zbuffer`).
With an observed depth map, a pixel keeps a label only from points whose depth agrees with the
measurement within ``depth_tol_m``: points hidden by something that is not in the cloud (an
occluder removed as background, or points pushed through a surface by pose error) do not leak
into the map, and splats that spill over a silhouette onto farther background are cut back.
Pixels without a measurement (depth 0) fall back to the plain z-buffer.
"""
from __future__ import annotations

import numpy as np


def zbuffer(points_w: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int,
            splat_px: int = 1, depth_m: np.ndarray | None = None, depth_tol_m: float = 0.01,
            depth_min_m: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Render points as square splats into a z-buffer; returns (depth, index).

    depth: float32 H×W planar depth (m) of the point chosen for each pixel, 0 = none;
    index: int64 H×W index into ``points_w`` of that point, −1 = none.

    A pixel's candidates are the splats covering it. Without ``depth_m`` the visible surface is
    the nearest candidate, and candidates within ``depth_tol_m`` behind it belong to it. With
    ``depth_m`` (H×W metres, 0 = no measurement) the measured depth is the visible surface: only
    candidates within ``depth_tol_m`` of it are kept (pixels without a measurement fall back to
    the nearest-candidate rule). Of the kept candidates, the point projecting closest to the pixel
    centre wins (ties: the nearer one), so splats fill holes without shifting depths on slanted
    surfaces. Points closer than ``depth_min_m`` (or behind the camera) are ignored.
    """
    if splat_px < 0:
        raise ValueError(f"splat_px must be >= 0, got {splat_px}")
    if depth_m is not None and depth_m.shape != (height, width):
        raise ValueError(f"depth map is {depth_m.shape}, expected {(height, width)}")
    pts = np.asarray(points_w, dtype=np.float64).reshape(-1, 3)
    T_cam_world = np.linalg.inv(np.asarray(T_world_cam, dtype=np.float64))
    p = pts @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    depth = np.zeros((height, width), np.float32)
    index = np.full((height, width), -1, np.int64)
    front = np.nonzero(p[:, 2] > depth_min_m)[0]
    z = p[front, 2]
    u = np.floor(K[0, 0] * p[front, 0] / z + K[0, 2] + 0.5).astype(np.int64)
    v = np.floor(K[1, 1] * p[front, 1] / z + K[1, 2] + 0.5).astype(np.int64)
    near = (u >= -splat_px) & (u < width + splat_px) & (v >= -splat_px) & (v < height + splat_px)
    front, z, u, v = front[near], z[near], u[near], v[near]
    offs = np.arange(-splat_px, splat_px + 1)
    du, dv = (a.ravel() for a in np.meshgrid(offs, offs))
    uu = (u[None, :] + du[:, None]).ravel()
    vv = (v[None, :] + dv[:, None]).ravel()
    off2 = np.repeat(du * du + dv * dv, len(front))
    zz = np.tile(z, len(du))
    ii = np.tile(front, len(du))
    keep = (uu >= 0) & (uu < width) & (vv >= 0) & (vv < height)
    pix = vv[keep] * width + uu[keep]
    zz, ii, off2 = zz[keep], ii[keep], off2[keep]
    if depth_m is not None:
        obs = depth_m.ravel()[pix]
        ok = (obs <= 0) | (np.abs(zz - obs) <= depth_tol_m)
        pix, zz, ii, off2 = pix[ok], zz[ok], ii[ok], off2[ok]
    zmin = np.full(width * height, np.inf)
    np.minimum.at(zmin, pix, zz)
    same_surface = zz <= zmin[pix] + depth_tol_m
    pix, zz, ii, off2 = pix[same_surface], zz[same_surface], ii[same_surface], off2[same_surface]
    key = off2.astype(np.int64) << 40 | np.rint(zz * 1e6).astype(np.int64)  # offset first, then depth (µm)
    best = np.full(width * height, np.iinfo(np.int64).max)
    np.minimum.at(best, pix, key)
    win = key == best[pix]
    depth.ravel()[pix[win]] = zz[win]
    index.ravel()[pix[win]] = ii[win]
    return depth, index


def project_labels(points_w: np.ndarray, labels: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
                   width: int, height: int, depth_m: np.ndarray | None = None, depth_tol_m: float = 0.01,
                   splat_px: int = 1) -> np.ndarray:
    """Z-buffer projection of labelled world points into one frame → int32 H×W label map (−1 = no label).

    labels: N integers ≥ 0, one per point. With ``depth_m`` (H×W metres, 0 = no measurement), a
    pixel keeps its label only where the z-buffer depth agrees with the observed depth within
    ``depth_tol_m`` (occlusion test). ``splat_px``: half-size of the square splat, so that a dense
    cloud leaves no holes.
    """
    labels = np.asarray(labels).reshape(-1)
    if len(labels) != len(np.asarray(points_w).reshape(-1, 3)):
        raise ValueError(f"{len(labels)} labels for {len(np.asarray(points_w).reshape(-1, 3))} points")
    if len(labels) and labels.min() < 0:
        raise ValueError("labels must be >= 0 (−1 is reserved for 'no label')")
    _, index = zbuffer(points_w, K, T_world_cam, width, height, splat_px, depth_m, depth_tol_m)
    out = np.full((height, width), -1, np.int32)
    hit = index >= 0
    out[hit] = labels[index[hit]]
    return out


def foreground_mask(points_w: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int,
                    depth_m: np.ndarray | None = None, depth_tol_m: float = 0.01, splat_px: int = 1) -> np.ndarray:
    """bool H×W: pixels covered by the projected points (with the same depth test as :func:`project_labels`)."""
    n = len(np.asarray(points_w).reshape(-1, 3))
    return project_labels(points_w, np.zeros(n, np.int32), K, T_world_cam, width, height,
                          depth_m, depth_tol_m, splat_px) >= 0
