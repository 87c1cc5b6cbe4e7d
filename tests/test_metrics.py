"""Golden cases of the per-frame metrics, the boundary measure, the 3-D metric and the aggregation."""
import math

import numpy as np
import pytest
from scipy import ndimage

from selfseg.eval.aggregate import bootstrap_ci, mean_metrics, per_video, summarize_folds
from selfseg.eval.metrics import (METRIC_KEYS, boundary_map, boundary_radius, disk, frame_metrics,
                                  segment_metrics)


def two_objects():
    """A: 4×2 = 8 px (id 1), B: 4×4 = 16 px (id 2), side by side in a 12×12 image."""
    gt = np.zeros((12, 12), np.uint16)
    gt[4:8, 2:4] = 1
    gt[4:8, 4:8] = 2
    return gt


def test_identity_and_relabelling_score_one():
    gt = two_objects()
    for pred in (gt, np.where(gt == 1, 7, np.where(gt == 2, 3, 0))):
        m = frame_metrics(pred, gt)
        assert all(m[k] == 1.0 for k in METRIC_KEYS), m
        assert (m["n_gt"], m["n_pred"], m["n_matched"]) == (2, 2, 2)


def test_split_case_hand_computed():
    gt = np.zeros((12, 12), np.uint16)
    gt[4:8, 2:8] = 5  # one object, 24 px
    pred = np.zeros_like(gt)
    pred[4:8, 2:4] = 1  # 8 px piece
    pred[4:8, 4:8] = 2  # 16 px piece: IoU 2/3 beats 1/3
    m = frame_metrics(pred, gt)
    assert m["P"] == pytest.approx(1.0)  # the matched piece lies inside the object
    assert m["R"] == pytest.approx(16 / 24) and m["IoU"] == pytest.approx(16 / 24)
    assert m["overlap_P"] == pytest.approx(16 / 24)  # UOIS penalises the extra piece
    assert m["overlap_R"] == pytest.approx(16 / 24) and m["overlap_F"] == pytest.approx(16 / 24)
    assert m["F75"] == 1.0  # matched F = 2·16/(24+16) = 0.8


def test_merge_case_hand_computed():
    gt = two_objects()
    pred = (gt > 0).astype(np.uint16)  # one 24 px segment over A (8 px) and B (16 px)
    m = frame_metrics(pred, gt)
    # B is matched (IoU 16/24 > 8/24): P = 16/24, R = 1, IoU = 16/24; A is unmatched and scores 0
    assert m["P"] == pytest.approx((0 + 16 / 24) / 2)
    assert m["R"] == pytest.approx((0 + 1) / 2)
    assert m["IoU"] == pytest.approx((0 + 16 / 24) / 2)
    assert m["overlap_P"] == pytest.approx(16 / 24) and m["overlap_R"] == pytest.approx(16 / 24)
    assert m["F75"] == pytest.approx(0.5)  # F(B) = 32/40 = 0.8, A unmatched
    assert m["n_matched"] == 1


def test_zero_overlap_pair_is_unmatched():
    gt = np.zeros((4, 10), np.uint16)
    gt[0, :] = 1  # A: 10 px
    gt[1, :] = 2  # B: 10 px
    pred = np.zeros_like(gt)
    pred[0, :9] = 1  # X: 9 px of A ...
    pred[1, 0] = 1  # ... and 1 px of B
    pred[0, 9] = 2  # Y: 1 px of A; the rest of B is predicted as 0
    m = segment_metrics(pred, gt, return_matches=True)
    # Hungarian picks A-X (cost 2/11) + B-Y (cost 1, zero overlap) over A-Y + B-X (0.9 + 18/19)
    assert m["matches"] == {1: 1} and m["n_matched"] == 1
    assert m["P"] == pytest.approx(0.9 / 2) and m["R"] == pytest.approx(0.9 / 2)
    assert m["IoU"] == pytest.approx(9 / 11 / 2)


def test_predictions_outside_foreground_are_ignored():
    gt = two_objects()
    pred = gt.copy()
    pred[0:3, :] = 9  # segments entirely on background
    pred[10:, :] = 4
    m = frame_metrics(pred, gt)
    assert m["n_pred"] == 2 and m["overlap_P"] == 1.0 and m["boundary_P"] == 1.0


def test_empty_cases():
    gt = two_objects()
    none = frame_metrics(np.zeros_like(gt), gt)  # objects, no prediction
    assert (none["P"], none["R"], none["IoU"], none["F75"]) == (0.0, 0.0, 0.0, 0.0)
    assert (none["overlap_P"], none["overlap_R"], none["overlap_F"]) == (1.0, 0.0, 0.0)  # UOIS convention
    assert (none["boundary_P"], none["boundary_R"], none["boundary_F"]) == (1.0, 0.0, 0.0)
    no_gt = frame_metrics(gt, np.zeros_like(gt))  # no objects: not scored
    assert no_gt["n_gt"] == 0 and no_gt["n_pred"] == 0 and all(math.isnan(no_gt[k]) for k in METRIC_KEYS)
    agg = mean_metrics([{"video_id": "a", **no_gt}, {"video_id": "a", **none}])
    assert agg["n_frames"] == 1 and agg["overlap_P"] == 1.0


def test_boundary_radius():
    assert boundary_radius(480, 640) == 3  # ceil(0.003 · 800) = ceil(2.4)
    assert boundary_radius(120, 160) == 1  # ceil(0.6)
    assert disk(1).sum() == 5 and disk(3).sum() == 29


def _edt_boundary_pr(pred_mask, gt_mask, r):
    """Independent reference: boundary pixels within Euclidean distance r of the other boundary."""
    pb, gb = boundary_map(pred_mask), boundary_map(gt_mask)
    d_to_gt = ndimage.distance_transform_edt(~gb)
    d_to_pred = ndimage.distance_transform_edt(~pb)
    return (d_to_gt[pb] <= r).mean(), (d_to_pred[gb] <= r).mean()


def test_boundary_scores_match_distance_reference():
    h, w = 480, 640
    r = boundary_radius(h, w)
    gt = np.zeros((h, w), np.uint16)
    gt[100:220, 150:330] = 1
    yy, xx = np.mgrid[:h, :w]
    gt[(yy - 330) ** 2 + (xx - 420) ** 2 < 70 ** 2] = 2
    for shift in (1, 3, 6):
        pred = np.roll(gt, shift, axis=1)  # fg clipping trims the parts that leave the objects
        m = frame_metrics(pred, gt)
        clipped = np.where(gt > 0, pred, 0)
        tp = {k: [] for k in ("p", "r", "np", "nr")}
        for g in (1, 2):
            pm, gm = clipped == g, gt == g
            p, rr = _edt_boundary_pr(pm, gm, r)
            tp["p"].append(p * boundary_map(pm).sum())
            tp["np"].append(boundary_map(pm).sum())
            tp["r"].append(rr * boundary_map(gm).sum())
            tp["nr"].append(boundary_map(gm).sum())
        assert m["boundary_P"] == pytest.approx(sum(tp["p"]) / sum(tp["np"]))
        assert m["boundary_R"] == pytest.approx(sum(tp["r"]) / sum(tp["nr"]))
    small_shift = frame_metrics(np.roll(gt, 2, axis=1), gt)
    assert small_shift["overlap_F"] < 1.0 and small_shift["boundary_R"] > 0.9
    large_shift = frame_metrics(np.roll(gt, 8, axis=1), gt)
    assert large_shift["boundary_F"] < small_shift["boundary_F"]


def test_aggregation_and_bootstrap():
    frames = [{"video_id": "a", "n_gt": 1, **{k: 1.0 for k in METRIC_KEYS}},
              {"video_id": "a", "n_gt": 1, **{k: 0.0 for k in METRIC_KEYS}},
              {"video_id": "b", "n_gt": 2, **{k: 0.25 for k in METRIC_KEYS}}]
    videos = per_video(frames)
    assert videos["a"]["IoU"] == 0.5 and videos["a"]["n_frames"] == 2 and videos["b"]["IoU"] == 0.25
    assert mean_metrics(frames)["IoU"] == pytest.approx(1.25 / 3)  # mean over frames, not videos
    ci = bootstrap_ci(videos, n_boot=500, seed=1)
    lo, hi = ci["IoU"]
    assert 0.25 <= lo <= 1.25 / 3 <= hi <= 0.5  # resampled means lie between the two video means
    assert bootstrap_ci(videos, n_boot=500, seed=1) == ci  # seeded
    folds = [{"fold": k, "metrics": {**{m: v for m in METRIC_KEYS}, "n_frames": 3}, "per_video": {f"v{k}": {
        **{m: v for m in METRIC_KEYS}, "n_frames": 3}}, "timings": {"ms_per_frame": 2.0}}
        for k, v in enumerate([0.2, 0.4, 0.6])]
    s = summarize_folds(folds, n_boot=200)
    assert s["mean"]["IoU"] == pytest.approx(0.4) and s["std"]["IoU"] == pytest.approx(0.2)
    assert s["n_frames"] == 9 and s["folds"] == [0, 1, 2]


def test_points_metric_on_labelled_cloud(analytic_dataset):
    import trimesh

    from selfseg.analytic import two_box_scenes
    from selfseg.dataset import Dataset
    from selfseg.eval.points import PointsEvaluator, evaluate_points, gt_point_labels

    ds = Dataset(analytic_dataset)
    scene = two_box_scenes()[0]  # meshes already in world coordinates; the GT pose is the identity
    models = {obj: mesh for mesh, obj in scene}
    pts = [trimesh.sample.sample_surface(mesh, n, seed=i)[0] for i, ((mesh, _), n) in enumerate(zip(scene, (300, 200)))]
    table = np.array([[0.3, 0.3, 0.0], [-0.3, 0.25, 0.0]])  # far from any object → GT 0, not scored
    points = np.concatenate(pts + [table])
    gt = np.r_[np.full(300, 1), np.full(200, 2), 0, 0]
    assert np.array_equal(gt_point_labels(points, ds, "000000", models=models), gt)
    top = np.array([[-0.08, 0.0, 0.08 + 0.005], [-0.08, 0.0, 0.08 + 0.02]])  # 5 mm and 2 cm above box 1
    assert gt_point_labels(top, ds, "000000", models=models).tolist() == [1, 0]

    perfect = evaluate_points(points, np.r_[np.full(300, 4), np.full(200, 9), 1, 1], ds, "000000", models=models)
    assert perfect["IoU"] == 1.0 and perfect["n_points_scored"] == 500
    merged = evaluate_points(points, (gt > 0).astype(int), ds, "000000", models=models)
    assert merged["P"] == pytest.approx(0.3) and merged["R"] == pytest.approx(0.5)
    assert merged["IoU"] == pytest.approx(0.3)  # box 1 matched: 300/500; box 2 unmatched
    T = np.eye(4)
    T[:3, 3] = [0.1, 0, 0]
    shifted = evaluate_points(points - [0.1, 0, 0], np.r_[np.full(300, 4), np.full(200, 9), 1, 1], ds, "000000",
                              T_world_points=T, models=models)
    assert shifted["IoU"] == 1.0

    ev = PointsEvaluator(ds, n_boot=50)
    ev.process("000000", points, np.r_[np.full(300, 4), np.full(200, 9), 1, 1], models=models)
    ev.process("000000", points, (gt > 0).astype(int), models=models)
    assert ev.evaluate()["metrics"]["IoU"] == pytest.approx((1.0 + 0.3) / 2)
    assert ev.evaluate()["per_video"]["000000"]["n_frames"] == 2
