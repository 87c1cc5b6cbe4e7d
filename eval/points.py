"""The Table II metric: segmentation of a reconstructed point cloud, scored against the GT objects.

A point's ground-truth label is the instance id of the nearest ground-truth object surface
(the dataset's models placed at their ground-truth poses), or 0 when that surface is farther
than ``GT_MAX_DIST_M`` = 1 cm (table, background, reconstruction noise). Points with label 0 are
not scored, as background pixels are not scored in 2D. The matching and the metrics are those
of :func:`selfseg.eval.metrics.segment_metrics` on points instead of pixels (no boundary metrics).
"""
from __future__ import annotations

import numpy as np

from selfseg.dataset import Dataset, DatasetError
from selfseg.eval.aggregate import BOOTSTRAP_SEED, N_BOOTSTRAP, bootstrap_ci, mean_metrics, per_video
from selfseg.eval.metrics import OVERLAP_KEYS, PAPER_KEYS, segment_metrics
from selfseg.poses import transform_points
from selfseg.raycast import RaycastScene

GT_MAX_DIST_M = 0.01
POINT_KEYS = PAPER_KEYS + OVERLAP_KEYS


def load_model_m(dataset: Dataset, obj_id: int):
    """A dataset model as a trimesh in metres (files are in millimetres)."""
    import trimesh

    path = dataset.model_path(obj_id)
    if not path.is_file():
        raise DatasetError(f"{path}: missing model of object {obj_id}")
    mesh = trimesh.load(path, force="mesh", process=False)
    mesh.apply_scale(0.001)
    return mesh


def gt_object_poses(dataset: Dataset, video_id: str) -> list[tuple[int, int, np.ndarray]]:
    """(inst_id, obj_id, T_world_model) of each GT object of a video, in the world frame of its camera poses.

    Poses come from the first frame: T_world_model = T_world_cam · T_cam_model (scenes are static).
    """
    video = dataset.labeled(video_id)
    f0 = video.frame_ids[0]
    T_world_cam = video.T_world_cam(f0)
    out = [(rec["inst_id"], rec["obj_id"], T_world_cam @ np.asarray(rec["T_cam_model"])) for rec in video.gt(f0)]
    if not out:
        raise DatasetError(f"{dataset.root}: video {video_id} has no ground-truth objects in frame {f0}")
    return out


def gt_scene(dataset: Dataset, video_id: str, models: dict | None = None) -> RaycastScene:
    """The video's GT objects (:func:`gt_object_poses`) in the world frame of its camera poses, tagged by
    instance id. ``models`` ({obj_id: mesh in metres, model frame}) overrides the dataset's PLY files."""
    objects = gt_object_poses(dataset, video_id)
    meshes = [models[obj] if models is not None and obj in models else load_model_m(dataset, obj)
              for _, obj, _ in objects]
    return RaycastScene.from_meshes(meshes, [T for _, _, T in objects], [inst for inst, _, _ in objects])


def gt_point_labels(points_world: np.ndarray, dataset: Dataset, video_id: str, max_dist_m: float = GT_MAX_DIST_M,
                    models: dict | None = None) -> np.ndarray:
    """Instance id of the nearest GT object surface for each world point (N×3, m); 0 beyond ``max_dist_m``."""
    return gt_scene(dataset, video_id, models).nearest_id(np.asarray(points_world, dtype=np.float64), max_dist_m)


def evaluate_points(points: np.ndarray, pred_labels: np.ndarray, dataset: Dataset, video_id: str,
                    T_world_points: np.ndarray | None = None, max_dist_m: float = GT_MAX_DIST_M,
                    models: dict | None = None) -> dict:
    """Score a point-cloud segmentation of one video.

    points: N×3 (m) in the dataset's world frame (that of ``scene_camera.json``), or in any frame
    mapped to it by ``T_world_points`` (4×4; e.g. the first camera's pose for a reconstruction
    anchored there). pred_labels: N integer segment ids (0 = unlabeled). Returns the metrics of
    :data:`POINT_KEYS` plus n_gt, n_pred, n_matched and n_points_scored.
    """
    pts = np.asarray(points, dtype=np.float64)
    labels = np.asarray(pred_labels)
    if pts.ndim != 2 or pts.shape[1] != 3 or labels.shape != (len(pts),):
        raise ValueError(f"points must be N×3 and labels N, got {pts.shape} and {labels.shape}")
    if T_world_points is not None:
        pts = transform_points(pts, T_world_points)
    gt = gt_point_labels(pts, dataset, video_id, max_dist_m, models)
    out = segment_metrics(labels, gt)
    out = {k: out[k] for k in POINT_KEYS + ("n_gt", "n_pred", "n_matched")}
    out["n_points_scored"] = int(np.count_nonzero(gt))
    return out


def adjusted_rand_index(a: np.ndarray, b: np.ndarray) -> float:
    """Adjusted Rand index (Hubert & Arabie) of two labelings of the same N points (any integer
    labels; −1 counts as one more cluster): 1 = the same partition, ≈0 = chance agreement."""
    a, b = np.asarray(a).ravel(), np.asarray(b).ravel()
    if a.shape != b.shape:
        raise ValueError(f"labelings differ in length: {a.shape} vs {b.shape}")
    _, ia = np.unique(a, return_inverse=True)
    _, ib = np.unique(b, return_inverse=True)
    table = np.bincount(ia.ravel() * (ib.max(initial=0) + 1) + ib.ravel()).astype(np.float64)
    comb = lambda x: float(np.sum(x * (x - 1) / 2))  # noqa: E731
    s_ij, s_a, s_b = comb(table), comb(np.bincount(ia.ravel()).astype(float)), comb(np.bincount(ib.ravel()).astype(float))
    total = len(a) * (len(a) - 1) / 2
    expected = s_a * s_b / total if total else 0.0
    denom = 0.5 * (s_a + s_b) - expected
    return 1.0 if denom == 0 else float((s_ij - expected) / denom)


class PointsEvaluator:
    """detectron2-style accumulator of per-video point-cloud scores (one cloud per video).

    ``evaluate()`` gives {metrics, per_video, ci95} over :data:`POINT_KEYS`; with
    :func:`selfseg.eval.provenance.provenance` (task ``"3d"``), ``fold`` and ``timings`` it makes a
    result record for :func:`selfseg.eval.protocol.write_result`, which Table II is built from.
    """

    def __init__(self, dataset: Dataset, max_dist_m: float = GT_MAX_DIST_M, n_boot: int = N_BOOTSTRAP,
                 seed: int = BOOTSTRAP_SEED):
        self.dataset = dataset
        self.max_dist_m = max_dist_m
        self.n_boot = n_boot
        self.seed = seed
        self.records: list[dict] = []

    def reset(self) -> None:
        self.records = []

    def process(self, video_id: str, points: np.ndarray, pred_labels: np.ndarray,
                T_world_points: np.ndarray | None = None, models: dict | None = None) -> dict:
        rec = {"video_id": video_id, **evaluate_points(points, pred_labels, self.dataset, video_id, T_world_points,
                                                       self.max_dist_m, models)}
        self.records.append(rec)
        return rec

    def evaluate(self) -> dict:
        videos = per_video(self.records, POINT_KEYS)
        return {"metrics": mean_metrics(self.records, POINT_KEYS), "per_video": videos,
                "ci95": bootstrap_ci(videos, POINT_KEYS, self.n_boot, self.seed)}
