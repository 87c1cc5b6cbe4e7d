"""Rigid registration of segment point clouds (FPFH + RANSAC, then ICP) and its precision/recall.

Used by pruning criterion 2 and by the V4 ablation. The voxel size sets everything: clouds are
downsampled to it, normals use a 2-voxel radius, FPFH a 5-voxel radius, RANSAC accepts
correspondences within 1.5 voxels and ICP (point-to-plane) within 1 voxel. Segments are small
(a few cm), so the default voxel is fine (5 mm) and registration takes milliseconds.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from selfseg.library_log import captured
from selfseg.poses import transform_points

MIN_POINTS = 8  # fewer downsampled points than this cannot be registered meaningfully


class RegistrationError(ValueError):
    """A cloud is too small (after downsampling) to register."""


class Registration(NamedTuple):
    """``T_tgt_src`` maps source points into the target frame; fitness and inlier RMSE are ICP's
    (share of downsampled source points with a target point within one voxel, and their RMSE)."""

    T_tgt_src: np.ndarray
    fitness: float
    rmse: float


def _cloud(points: np.ndarray, voxel_m: float, name: str):
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{name}: expected N×3 points, got shape {pts.shape}")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).voxel_down_sample(voxel_m)
    if len(pcd.points) < MIN_POINTS:
        raise RegistrationError(f"{name}: {len(pcd.points)} points after {voxel_m} m downsampling "
                                f"(need {MIN_POINTS})")
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel_m, max_nn=30))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel_m, max_nn=100))
    return pcd, fpfh


def register(src_pts: np.ndarray, tgt_pts: np.ndarray, voxel_m: float = 0.005, *, seed: int = 0,
             ransac_iters: int = 100_000, ransac_confidence: float = 0.999, icp_iters: int = 50) -> Registration:
    """Align ``src_pts`` (N×3) to ``tgt_pts`` (M×3): global RANSAC on FPFH matches, ICP refine.

    Raises :class:`RegistrationError` when a cloud has fewer than ``MIN_POINTS`` points after
    downsampling. ``seed`` seeds open3d's RANSAC sampler. What open3d prints (e.g. "Too few
    correspondences" warnings) goes to the run's library log (:mod:`selfseg.library_log`).
    """
    if voxel_m <= 0:
        raise ValueError(f"voxel_m must be positive, got {voxel_m}")
    reg = o3d.pipelines.registration
    with captured():
        src, fs = _cloud(src_pts, voxel_m, "source")
        tgt, ft = _cloud(tgt_pts, voxel_m, "target")
        o3d.utility.random.seed(seed)
        dist = 1.5 * voxel_m
        ransac = reg.registration_ransac_based_on_feature_matching(
            src, tgt, fs, ft, True, dist, reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(dist)],
            reg.RANSACConvergenceCriteria(ransac_iters, ransac_confidence))
        icp = reg.registration_icp(src, tgt, voxel_m, ransac.transformation,
                                   reg.TransformationEstimationPointToPlane(),
                                   reg.ICPConvergenceCriteria(max_iteration=icp_iters))
    return Registration(np.asarray(icp.transformation).copy(), float(icp.fitness), float(icp.inlier_rmse))


def precision_recall(src_pts: np.ndarray, tgt_pts: np.ndarray, T_tgt_src: np.ndarray,
                     dist_thresh_m: float) -> tuple[float, float]:
    """(precision, recall) of the aligned source against the target.

    Precision: share of transformed source points within ``dist_thresh_m`` of a target point.
    Recall: share of target points within ``dist_thresh_m`` of a transformed source point.
    An empty cloud scores 0.
    """
    src = transform_points(src_pts, T_tgt_src)
    tgt = np.asarray(tgt_pts, dtype=np.float64)
    if len(src) == 0 or len(tgt) == 0:
        return 0.0, 0.0
    d_src, _ = cKDTree(tgt).query(src, distance_upper_bound=dist_thresh_m)
    d_tgt, _ = cKDTree(src).query(tgt, distance_upper_bound=dist_thresh_m)
    return float(np.mean(d_src <= dist_thresh_m)), float(np.mean(d_tgt <= dist_thresh_m))
