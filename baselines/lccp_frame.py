"""Baseline C: LCCP on each test frame (the paper's "LCCP on each test frame").

The foreground pixels with depth are back-projected to camera-frame points, normals are
estimated with open3d (k nearest neighbours, oriented towards the camera centre), and
:func:`selfseg.method.lccp.lccp_segment` segments them. Points of segments smaller than
``min_segment_points`` (and of unlabelled voxels) take the label of their nearest labelled point;
foreground pixels without depth optionally take the nearest labelled pixel's label.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from selfseg.baselines.simple import fill_from_nearest
from selfseg.dataset import Video
from selfseg.method.lccp import LCCPConfig, lccp_segment
from selfseg.method.overseg import prune_small
from selfseg.method_api import Method
from selfseg.raycast import backproject


@dataclass
class LCCPFrameConfig:
    lccp: LCCPConfig = field(default_factory=LCCPConfig)
    min_segment_points: int = 100  # pixels; smaller segments are absorbed by their nearest labelled neighbour
    normal_knn: int = 20  # neighbours for open3d normal estimation
    fill_unlabeled: bool = True  # foreground pixels without depth take the nearest labelled pixel's label

    def __post_init__(self):
        if self.min_segment_points < 1 or self.normal_knn < 3:
            raise ValueError("min_segment_points must be ≥ 1 and normal_knn ≥ 3")


def estimate_normals_cam(points: np.ndarray, knn: int) -> np.ndarray:
    """Unit normals of camera-frame points (m), oriented towards the camera centre (open3d)."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn))
    pc.orient_normals_towards_camera_location(np.zeros(3))
    return np.asarray(pc.normals)


def lccp_frame_labels(depth_m: np.ndarray, K: np.ndarray, fg_mask: np.ndarray, cfg: LCCPFrameConfig) -> np.ndarray:
    """H×W uint16 instance map (0 = none) of LCCP segments of one frame's foreground."""
    fg = fg_mask.astype(bool)
    out = np.zeros(depth_m.shape, np.int64)
    pts, vu = backproject(depth_m, K, fg)
    if len(pts) >= 3:
        normals = estimate_normals_cam(pts, cfg.normal_knn)
        lab = prune_small(lccp_segment(pts, normals, None, cfg.lccp, viewpoint=(0.0, 0.0, 0.0)),
                          cfg.min_segment_points)
        ok = lab >= 0
        if ok.any() and not ok.all():
            _, nn = cKDTree(pts[ok]).query(pts[~ok])
            lab[~ok] = lab[ok][nn]
        out[vu[:, 0], vu[:, 1]] = np.where(lab >= 0, lab + 1, 0)
    if cfg.fill_unlabeled:
        out = fill_from_nearest(out, fg)
    out[~fg] = 0
    return out.astype(np.uint16)


class LCCPFrame(Method):
    """LCCP on the back-projected foreground of each test frame (no training)."""

    name = "lccp-frame"
    config_cls = LCCPFrameConfig

    def segment(self, video: Video, frame_id: int, fg_mask: np.ndarray) -> np.ndarray:
        return lccp_frame_labels(video.depth_m(frame_id), video.K(frame_id), fg_mask, self.config)
