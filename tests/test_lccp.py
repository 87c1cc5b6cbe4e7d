"""VCCS + LCCP on analytic clouds (ray-cast from all around, 1 mm depth noise), and baseline C."""
import numpy as np
import pytest

from selfseg.analytic import box, cylinder, fused_cloud, make_dataset
from selfseg.dataset import Dataset
from selfseg.method.lccp import LCCPConfig, edge_validity, lccp_segment
from selfseg.method.overseg import OversegConfig, oversegment, prune_small
from selfseg.method.supervoxels import Supervoxels, supervoxel_clustering
from selfseg.registry import get_method_class


def big_segments(labels, min_points=200):
    """Point counts of segments with at least ``min_points`` points, largest first."""
    c = np.bincount(labels[labels >= 0])
    return np.sort(c[c >= min_points])[::-1]


def purity(labels, gt, s):
    return np.bincount(gt[labels == s]).max() / (labels == s).sum()


def test_box_on_plane_is_one_segment():
    P, N, _ = fused_cloud([box((0.08, 0.08, 0.08), (0, 0, 0.04))])
    assert P[:, 2].min() > 0.003  # the plane is removed
    lab = lccp_segment(P, N, None, LCCPConfig())
    assert (lab >= 0).all() and lab.max() == 0


def test_two_touching_boxes_of_different_heights_are_two_segments():
    P, N, gt = fused_cloud([box((0.08, 0.08, 0.08), (-0.04, 0, 0.04)), box((0.06, 0.05, 0.04), (0.03, 0, 0.02))])
    lab = prune_small(lccp_segment(P, N, None, LCCPConfig()), 200)
    assert len(big_segments(lab)) == 2
    assert (lab >= 0).mean() > 0.95
    assert min(purity(lab, gt, 0), purity(lab, gt, 1)) > 0.95
    assert np.bincount(gt[lab == 0]).argmax() != np.bincount(gt[lab == 1]).argmax()


def test_two_equal_boxes_side_by_side_stay_one_convex_segment():
    P, N, _ = fused_cloud([box((0.06, 0.08, 0.06), (-0.03, 0, 0.03)), box((0.06, 0.08, 0.06), (0.03, 0, 0.03))])
    assert len(big_segments(lccp_segment(P, N, None, LCCPConfig()))) == 1


def test_l_of_two_boxes_splits_at_the_concave_edge():
    # a lying box and a wider standing box at its end: concave edges all round the joint
    P, N, gt = fused_cloud([box((0.16, 0.04, 0.03), (0, 0, 0.015)), box((0.05, 0.07, 0.12), (0.105, 0, 0.06))])
    lab = prune_small(lccp_segment(P, N, None, LCCPConfig()), 200)
    assert len(big_segments(lab)) == 2
    assert min(purity(lab, gt, 0), purity(lab, gt, 1)) > 0.9
    # without the sanity criterion (PCL's example) a diagonal supervoxel contact joins the arms
    assert len(big_segments(lccp_segment(P, N, None, LCCPConfig(use_sanity_criterion=False)))) == 1


def _two_patch_sv(n_s, n_t, c_s, c_t) -> Supervoxels:
    z = np.zeros((2, 3))
    return Supervoxels(point_voxel=np.zeros(0, np.int64), voxel_label=np.zeros(0, np.int32),
                       point_label=np.zeros(0, np.int32), centroids=np.array([c_s, c_t], float),
                       normals=np.array([n_s, n_t], float) / np.linalg.norm([n_s, n_t], axis=1)[:, None],
                       colors=z, voxel_count=np.ones(2, np.int64), edges=np.array([[0, 1]], np.int32))


@pytest.mark.parametrize("n_s,n_t,c_s,c_t,kw,expected", [
    ((0, 0, 1), (1, 0, 0), (0, 0, 0.01), (0.01, 0, 0), {}, True),  # roof edge: convex
    ((0, 0, 1), (-1, 0, 0), (0, 0, 0.0), (0.01, 0, 0.01), {}, False),  # floor meets wall: concave, 90°
    ((0, 0, 1), (-np.sin(np.radians(5)), 0, np.cos(np.radians(5))), (0, 0, 0), (0.02, 0, 0.001), {}, True),  # 5° concave
    ((0, 0, 1), (0, 0, 1), (0, 0, 0), (0.02, 0, 0.01), {}, False),  # 1 cm step between parallel patches
    ((0, 0, 1), (0, 0, 1), (0, 0, 0), (0.02, 0, 0.01), {"use_smoothness_check": False}, True),
    ((0, 0, 1), (1, 0, 0), (0, 0, 0.01), (0.01, 0, 0), {"k_factor": 1}, False),  # no common convex neighbour
])
def test_edge_criteria(n_s, n_t, c_s, c_t, kw, expected):
    assert edge_validity(_two_patch_sv(n_s, n_t, c_s, c_t), LCCPConfig(**kw))[0] == expected


def test_vccs_supervoxels_have_seed_size_and_cover_a_plane():
    rng = np.random.default_rng(0)
    P = np.c_[rng.uniform(0, 0.3, (20000, 2)), rng.normal(0, 0.001, 20000)]
    sv = supervoxel_clustering(P, None, None, 0.0075, 0.03, viewpoint=(0.15, 0.15, 1.0))
    assert 60 <= sv.n <= 130  # (0.3 / 0.03)² = 100 seed cells
    assert (sv.point_label >= 0).all()
    assert np.allclose(np.abs(sv.normals[:, 2]), 1, atol=0.05) and (sv.normals[:, 2] > 0).all()
    again = supervoxel_clustering(P, None, None, 0.0075, 0.03, viewpoint=(0.15, 0.15, 1.0))
    assert np.array_equal(sv.point_label, again.point_label)  # deterministic


def test_bad_input_fails_clearly():
    with pytest.raises(ValueError, match="N×3"):
        lccp_segment(np.zeros((0, 3)), None, None, LCCPConfig())
    with pytest.raises(ValueError, match="NaN"):
        lccp_segment(np.full((5, 3), np.nan), None, None, LCCPConfig())


@pytest.mark.slow
def test_lccp_frame_baseline_on_an_analytic_frame(tmp_path):
    scene = [(box((0.08, 0.08, 0.08), (-0.1, 0.0, 0.04)), 1), (box((0.06, 0.1, 0.05), (0.08, 0.02, 0.025)), 2),
             (cylinder(0.035, 0.1, (0.0, -0.1, 0.05)), 3)]
    ds = Dataset(make_dataset(tmp_path / "d", [scene], n_frames=1, width=320, height=240, fx=300.0))
    lv = ds.labeled(ds.video_ids[0])
    fid = lv.frame_ids[0]
    gt = lv.inst(fid)
    fg = gt > 0
    method = get_method_class("lccp-frame")()
    pred = method.segment(ds.video(ds.video_ids[0]), fid, fg)
    assert pred.dtype == np.uint16 and pred.shape == gt.shape
    assert (pred[~fg] == 0).all() and (pred[fg] > 0).all()
    for k in (1, 2, 3):  # each object is mostly one predicted segment of its own
        ids, cnt = np.unique(pred[gt == k], return_counts=True)
        top = ids[cnt.argmax()]
        assert cnt.max() / cnt.sum() > 0.8
        assert (gt[pred == top] == k).mean() > 0.9
    assert len(np.unique(pred[fg])) >= 3


def test_density_scaled_pruning_threshold():
    """Pruning by area: 16 random points per cm² of a plane; 5 cm² then means ~80 points, 4 per cm² ~20."""
    from selfseg.method.overseg import OversegConfig, min_points, surface_density_per_cm2

    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(0, 0.2, (6400, 2)), np.zeros(6400)]  # 400 cm², 16 per cm²
    assert surface_density_per_cm2(pts) == pytest.approx(16.0, rel=0.1)
    assert surface_density_per_cm2(pts[:1600]) == pytest.approx(4.0, rel=0.15)
    assert min_points(pts, OversegConfig(min_segment_area_cm2=5.0)) == pytest.approx(80, rel=0.1)
    assert min_points(pts[:1600], OversegConfig(min_segment_area_cm2=5.0)) == pytest.approx(20, rel=0.15)
    assert min_points(pts, OversegConfig()) == 200  # area 0: the paper's fixed count
