"""Segment graphs: 3D adjacency edges, weakly connected components, file round trip."""
import numpy as np
import pytest

from selfseg.analytic import box, fused_cloud
from selfseg.fileio import FileFormatError
from selfseg.method.segment_graph import SegmentGraph, boundary_pairs, build_segment_graph


@pytest.fixture(scope="module")
def three_boxes():
    """Boxes 0 and 1 touch; box 2 stands 6 cm away. Labels = ground-truth box index."""
    return fused_cloud([box((0.06, 0.06, 0.06), (-0.03, 0, 0.03)), box((0.05, 0.05, 0.04), (0.025, 0, 0.02)),
                        box((0.05, 0.05, 0.05), (0.12, 0.0, 0.025))])


def test_touching_boxes_share_one_edge_separated_box_is_its_own_component(three_boxes):
    P, _, gt = three_boxes
    g = build_segment_graph(P, gt.astype(np.int32), adjacency_radius_m=0.0075)
    assert g.edges.tolist() == [[0, 1]]
    comps = g.components()
    assert [c.tolist() for c in comps] == [[0, 1], [2]]
    assert g.sizes.sum() == len(P) and np.array_equal(g.point_indices(2), np.nonzero(gt == 2)[0])
    assert np.allclose(g.centroids[2][:2], (0.12, 0.0), atol=0.005)


def test_boundary_pairs_count_grows_with_the_shared_boundarys_length():
    """A 12 × 4 × 4 cm box's seen surface (no bottom: it stands on the table) split two ways: across at x = 0 (a
    12-cm boundary over the top and the two long sides) and lengthwise at y = 0 (20 cm: the top's 12 and the two
    ends' 4). The pairs behind the single edge number as the boundary lengths do, and their unique rows are the
    graph's edges."""
    P, _, _ = fused_cloud([box((0.12, 0.04, 0.04), (0.0, 0.0, 0.02))])
    counts = []
    for lab in ((P[:, 0] > 0).astype(np.int32), (P[:, 1] > 0).astype(np.int32)):
        pairs = boundary_pairs(P, lab, 0.0075)
        assert np.unique(pairs, axis=0).tolist() == build_segment_graph(P, lab).edges.tolist() == [[0, 1]]
        counts.append(len(pairs))
    assert 1.4 < counts[1] / counts[0] < 2.0  # 20 / 12 ≈ 1.67


def test_unlabelled_points_are_ignored_and_labels_must_be_consecutive(three_boxes):
    P, _, gt = three_boxes
    lab = gt.astype(np.int32).copy()
    lab[gt == 1] = -1  # without box 1 nothing touches
    lab[gt == 2] = 1
    g = build_segment_graph(P, lab)
    assert len(g.edges) == 0 and len(g.components()) == 2
    with pytest.raises(ValueError, match="consecutive"):
        build_segment_graph(P, np.where(gt == 1, 5, gt).astype(np.int32))


def test_save_load_round_trip(tmp_path, three_boxes):
    P, _, gt = three_boxes
    g = build_segment_graph(P, gt.astype(np.int32))
    g.save(tmp_path / "graph.npz")
    h = SegmentGraph.load(tmp_path / "graph.npz")
    for k in ("labels", "edges", "centroids", "sizes"):
        assert np.array_equal(getattr(g, k), getattr(h, k))
    assert h.adjacency_radius_m == g.adjacency_radius_m
    (tmp_path / "bad.npz").write_bytes(b"not a graph")
    with pytest.raises(FileFormatError):
        SegmentGraph.load(tmp_path / "bad.npz")
