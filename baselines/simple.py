"""Reference methods that need no training: the oracle, one segment, 2-D components, depth clustering."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selfseg.dataset import LabeledVideo, Video
from selfseg.eval.metrics import unique_inverse
from selfseg.method_api import Method
from selfseg.raycast import backproject


class Oracle(Method):
    """Ground truth as prediction: scores 1.0 on every metric; a test of the harness."""

    name = "oracle"
    needs_ground_truth = True

    def segment(self, video: LabeledVideo, frame_id: int, fg_mask: np.ndarray) -> np.ndarray:
        return video.inst(frame_id)


class OneSegment(Method):
    """The whole foreground as one object."""

    name = "one-segment"

    def segment(self, video: Video, frame_id: int, fg_mask: np.ndarray) -> np.ndarray:
        return fg_mask.astype(np.uint16)


class ForegroundComponents(Method):
    """8-connected components of the foreground mask (cv2.connectedComponents)."""

    name = "fg-components"

    def segment(self, video: Video, frame_id: int, fg_mask: np.ndarray) -> np.ndarray:
        import cv2

        _, labels = cv2.connectedComponents(fg_mask.astype(np.uint8), connectivity=8)
        return labels.astype(np.uint16)


@dataclass
class DepthClusteringConfig:
    distance_m: float = 0.01  # points closer than this (m) join the same cluster
    voxel_m: float = 0.004  # points are first pooled into voxels of this size (m), for speed
    min_points: int = 30  # clusters with fewer foreground pixels are dropped, then filled as below
    fill_unlabeled: bool = True  # give foreground pixels without depth the label of the nearest labelled pixel

    def __post_init__(self):
        if not (self.distance_m > 0 and self.voxel_m > 0 and self.min_points >= 1):
            raise ValueError("distance_m and voxel_m must be positive, min_points ≥ 1")


class DepthClustering(Method):
    """Euclidean clustering of the back-projected foreground points (the classic tabletop baseline).

    Foreground pixels with depth become camera-frame points, pooled into ``voxel_m`` voxels
    (centroids); voxels closer than ``distance_m`` are linked (scipy cKDTree) and the connected
    components are the objects. Each pixel takes its voxel's cluster.
    """

    name = "depth-clustering"
    config_cls = DepthClusteringConfig

    def segment(self, video: Video, frame_id: int, fg_mask: np.ndarray) -> np.ndarray:
        return cluster_depth(video.depth_m(frame_id), video.K(frame_id), fg_mask, self.config)


def fill_from_nearest(labels: np.ndarray, fg: np.ndarray) -> np.ndarray:
    """``labels`` (H×W int, 0 = none) with each unlabelled pixel of the bool mask ``fg`` given the label of the
    nearest labelled pixel (Euclidean distance in pixels); unchanged when no pixel is labelled."""
    from scipy import ndimage

    if not (labels > 0).any() or not (fg & (labels == 0)).any():
        return labels
    _, (iy, ix) = ndimage.distance_transform_edt(labels == 0, return_indices=True)
    return np.where(fg & (labels == 0), labels[iy, ix], labels)


def cluster_depth(depth_m: np.ndarray, K: np.ndarray, fg_mask: np.ndarray, cfg: DepthClusteringConfig) -> np.ndarray:
    """H×W uint16 labels (0 = none) of Euclidean clusters of the foreground points; see :class:`DepthClustering`."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    out = np.zeros(depth_m.shape, np.int64)
    pts, vu = backproject(depth_m, K, fg_mask)
    if len(pts):
        _, voxel_of_point, counts = np.unique(np.floor(pts / cfg.voxel_m).astype(np.int64), axis=0,
                                              return_inverse=True, return_counts=True)
        voxel_of_point = voxel_of_point.ravel()
        centroids = np.zeros((len(counts), 3))
        np.add.at(centroids, voxel_of_point, pts)
        centroids /= counts[:, None]
        pairs = cKDTree(centroids).query_pairs(cfg.distance_m, output_type="ndarray")
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(counts),) * 2)
        _, comp = connected_components(graph, directed=False)
        labels = comp[voxel_of_point] + 1
        sizes = np.bincount(labels)
        labels[sizes[labels] < cfg.min_points] = 0
        out[vu[:, 0], vu[:, 1]] = labels
    fg = fg_mask.astype(bool)
    if cfg.fill_unlabeled:
        out = fill_from_nearest(out, fg)
    out[~fg] = 0
    ids, inv = unique_inverse(out)  # renumber clusters 1..n so they fit uint16
    return (inv.reshape(out.shape) + int(ids[0] != 0)).astype(np.uint16)
