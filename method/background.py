"""Background removal: find the support plane by RANSAC, drop it, everything below it and outliers.

Units: metres, world frame of the reconstruction. A plane is ``[a, b, c, d]`` with unit normal
(a, b, c) pointing up, towards the objects; a point's height above it is ``a·x + b·y + c·z + d``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class BackgroundError(RuntimeError):
    """No support plane could be found; the message names the scene and what was tried."""


@dataclass
class BackgroundConfig:
    """Support-plane RANSAC, outlier removal and the per-frame foreground masks."""

    distance_threshold_m: float = 0.006  # RANSAC inlier distance
    iterations: int = 1000  # RANSAC iterations per plane
    max_planes: int = 3  # planes tried, largest first, until one is near-horizontal
    min_plane_points: int = 2000  # a support plane has at least this many inliers
    max_tilt_deg: float = 60.0  # max angle between the plane normal and the up hint
    below_margin_m: float = 0.008  # points lower than this above the plane are removed (plane included)
    crop_to_plane_hull: bool = True  # drop points whose foot on the plane lies outside the inliers' hull
    outlier_neighbors: int = 20  # statistical outlier removal: neighbours ...
    outlier_std_ratio: float = 2.5  # ... and standard-deviation ratio
    min_object_points: int = 100  # fewer kept points: error (nothing stands on the plane)
    mask_depth_tol_m: float = 0.01  # per-frame foreground masks: z-buffer vs measured depth tolerance
    mask_splat_px: int = 1  # per-frame foreground masks: half-size of each point's square splat
    mask_plane_margin_m: float = 0.004  # per-frame masks: pixels measured lower above the plane are background
    seed: int = 0


def up_hint_from_poses(T_world_cam: np.ndarray) -> np.ndarray:
    """Approximate world 'up' from camera poses (F×4×4): the mean of the cameras' −y axes (OpenCV y points down)."""
    up = -np.asarray(T_world_cam)[:, :3, 1].mean(0)
    return up / np.linalg.norm(up)


def _plane_distance(pts: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """|a·x + b·y + c·z + d| of each point (N×3, m) from ``plane`` (4, unit normal), elementwise (no BLAS, so the
    same bits on any thread count)."""
    return np.abs(pts[:, 0] * plane[0] + pts[:, 1] * plane[1] + pts[:, 2] * plane[2] + plane[3])


def ransac_plane(pts: np.ndarray, threshold_m: float, iterations: int, rng: np.random.Generator,
                 n_eval: int = 4096, n_best: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """The support plane of ``pts`` (N×3, m) by MSAC: ``iterations`` planes through three random points are scored
    on ``n_eval`` random points, the ``n_best`` of them on every point, by the sum of squared distances capped at
    ``threshold_m`` (so among planes with as many inliers the one closest to them wins); the winner is then
    refitted by least squares to its inliers while that lowers the score. Returns (plane float64[4] with unit
    normal, indices of the points within ``threshold_m`` of it, ascending).

    Deterministic for a given ``rng`` state, whatever the thread count or load: Open3D's ``segment_plane``
    stops early when one of its threads finds a good plane, so its answer (and all that follows) changed with
    the scheduling.
    """
    n = len(pts)
    if n < 3:
        return np.array([0.0, 0.0, 1.0, 0.0]), np.zeros(0, np.int64)
    tri = pts[rng.integers(0, n, (iterations, 3))]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.sqrt((normal ** 2).sum(1))
    ok = norm > 1e-12
    if not ok.any():
        return np.array([0.0, 0.0, 1.0, 0.0]), np.zeros(0, np.int64)
    normal = normal[ok] / norm[ok, None]
    planes = np.c_[normal, -(normal * tri[ok, 0]).sum(1)]
    sample = pts[np.sort(rng.choice(n, min(n, n_eval), replace=False))]
    dist = np.abs(sample[None, :, 0] * planes[:, 0, None] + sample[None, :, 1] * planes[:, 1, None]
                  + sample[None, :, 2] * planes[:, 2, None] + planes[:, 3, None])
    screen = (np.minimum(dist, threshold_m) ** 2).sum(1)

    def cost(plane):
        return float((np.minimum(_plane_distance(pts, plane), threshold_m) ** 2).sum())

    best = min((planes[i] for i in np.argsort(screen, kind="stable")[:n_best]), key=cost)  # ties: the first
    best_cost = cost(best)
    for _ in range(3):  # least-squares refit: the normal is the inliers' direction of least spread
        p = pts[_plane_distance(pts, best) < threshold_m]
        if len(p) < 3:
            break
        c = p.mean(0)
        q = p - c
        normal = np.linalg.eigh(np.array([[(q[:, i] * q[:, j]).sum() for j in range(3)] for i in range(3)]))[1][:, 0]
        refit = np.r_[normal, -(normal * c).sum()]
        refit_cost = cost(refit)
        if refit_cost >= best_cost:
            break
        best, best_cost = refit, refit_cost
    return best.astype(np.float64), np.nonzero(_plane_distance(pts, best) < threshold_m)[0].astype(np.int64)


def remove_support_plane(points_w: np.ndarray, normals_w: np.ndarray | None, cfg: BackgroundConfig,
                         up_hint: np.ndarray | None = None, where: str = "scene") -> tuple[np.ndarray, np.ndarray]:
    """Find the support plane and the object points standing on it.

    Planes are found by RANSAC one after another (largest first, up to ``max_planes``); the first
    with at least ``min_plane_points`` inliers whose normal lies within ``max_tilt_deg`` of
    ``up_hint`` (if given) is the support. With both ``normals_w`` (N×3 unit) and a hint, RANSAC
    only sees points whose own normal lies within ``max_tilt_deg`` of the hint. Without a hint
    the largest plane is taken and oriented so that most non-plane points lie above it.
    Kept: points higher than ``below_margin_m``, over the convex hull of the plane's points
    (with normals: only those whose normal agrees with the plane's), surviving statistical
    outlier removal.

    Returns (keep: bool N, plane: float64[4], unit normal pointing up).
    """
    import open3d as o3d
    import open3d.core as o3c

    pts = np.asarray(points_w, dtype=np.float64).reshape(-1, 3)
    if len(pts) < cfg.min_plane_points:
        raise BackgroundError(f"{where}: only {len(pts)} points, fewer than min_plane_points={cfg.min_plane_points}")
    rng = np.random.default_rng(cfg.seed)
    remaining = np.arange(len(pts))
    if normals_w is not None and up_hint is not None:
        up = up_hint / np.linalg.norm(up_hint)
        remaining = np.nonzero(np.asarray(normals_w) @ up >= np.cos(np.radians(cfg.max_tilt_deg)))[0]
    plane = None
    tried = []
    for _ in range(cfg.max_planes):
        if len(remaining) < cfg.min_plane_points:
            break
        model, inliers = ransac_plane(pts[remaining], cfg.distance_threshold_m, cfg.iterations, rng)
        if len(inliers) < cfg.min_plane_points:
            tried.append(f"{len(inliers)} inliers")
            break
        if up_hint is not None:
            if model[:3] @ up_hint < 0:
                model = -model
            tilt = np.degrees(np.arccos(np.clip(model[:3] @ up_hint / np.linalg.norm(up_hint), -1, 1)))
            tried.append(f"{len(inliers)} inliers, tilt {tilt:.0f}°")
            if tilt <= cfg.max_tilt_deg:
                plane = model
                break
        else:
            h = pts @ model[:3] + model[3]
            off = np.abs(h) > cfg.distance_threshold_m
            if (h[off] > 0).sum() < (h[off] < 0).sum():
                model = -model
            plane = model
            break
        remaining = np.delete(remaining, inliers)
    if plane is None:
        raise BackgroundError(f"{where}: no support plane with >= {cfg.min_plane_points} inliers within "
                              f"{cfg.max_tilt_deg}° of up (tried: {'; '.join(tried) or 'none'})")

    height = pts @ plane[:3] + plane[3]
    keep = height > cfg.below_margin_m
    if cfg.crop_to_plane_hull:
        on_plane = np.abs(height) <= cfg.distance_threshold_m
        if normals_w is not None:  # where a wall meets the plane its points have sideways normals
            on_plane &= np.asarray(normals_w) @ plane[:3] >= np.cos(np.radians(cfg.max_tilt_deg))
        keep &= _over_plane_hull(pts, plane, on_plane, keep)
    idx = np.nonzero(keep)[0]
    if len(idx) > cfg.outlier_neighbors:
        _, inl = o3d.t.geometry.PointCloud(o3c.Tensor(pts[idx])).remove_statistical_outliers(
            cfg.outlier_neighbors, cfg.outlier_std_ratio)
        keep[idx[~inl.numpy().astype(bool)]] = False
    if keep.sum() < cfg.min_object_points:
        raise BackgroundError(f"{where}: only {int(keep.sum())} points above the support plane "
                              f"(min_object_points={cfg.min_object_points})")
    return keep, plane


def frame_foreground(depth_m: np.ndarray, K: np.ndarray, cfg: BackgroundConfig, where: str = "frame") -> np.ndarray:
    """bool H×W: pixels whose depth point (back-projected with K, camera frame) stands above the support
    plane (:func:`remove_support_plane` without an up hint: the largest plane); every pixel with depth,
    and a warning naming ``where``, if no plane is found."""
    from tqdm import tqdm

    from selfseg.raycast import backproject

    pts, vu = backproject(depth_m, K)
    out = np.zeros(depth_m.shape, bool)
    try:
        keep, _ = remove_support_plane(pts, None, cfg, where=where)
    except BackgroundError as e:
        tqdm.write(f"warning: {e}; using every pixel with depth as foreground")
        keep = np.ones(len(pts), bool)
    out[vu[keep, 0], vu[keep, 1]] = True
    return out


def plane_pixels(depth_m: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, plane: np.ndarray,
                 margin_m: float) -> np.ndarray:
    """bool H×W: pixels whose measured point (depth in m, K in the OpenCV convention) lies lower
    than ``margin_m`` above the plane, i.e. on the support or below it: background by definition."""
    from selfseg.raycast import backproject

    out = np.zeros(depth_m.shape, bool)
    p, vu = backproject(depth_m, K)
    n_cam = T_world_cam[:3, :3].T @ plane[:3]  # the plane in camera coordinates
    d_cam = plane[:3] @ T_world_cam[:3, 3] + plane[3]
    out[vu[:, 0], vu[:, 1]] = p @ n_cam + d_cam < margin_m
    return out


def _over_plane_hull(pts: np.ndarray, plane: np.ndarray, on_plane: np.ndarray, query: np.ndarray) -> np.ndarray:
    """bool N: ``query`` points whose foot on the plane lies inside the convex hull of the ``on_plane`` points."""
    from scipy.spatial import ConvexHull, Delaunay

    n = plane[:3]
    e1 = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    uv = np.stack([pts @ e1, pts @ e2], 1)
    hull_pts = uv[on_plane]
    hull = Delaunay(hull_pts[ConvexHull(hull_pts).vertices])
    out = np.zeros(len(pts), bool)
    out[query] = hull.find_simplex(uv[query]) >= 0
    return out
