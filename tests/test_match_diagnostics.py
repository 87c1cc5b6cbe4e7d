"""The matching step's diagnostics (counts with known answers) and its ground-truth scores
(merge precision/recall, cosine by object) on hand-built two-scene fixtures."""
import numpy as np
import pytest

from selfseg.eval.merges import cosine_by_object, merge_same_instance, merge_scores, relabel, segment_instances, summary
from selfseg.method.matching import SceneGraph
from selfseg.method.pruning import MatchDecision, NodeDecision
from selfseg.method.pseudolabels import diagnostics, merge_segments


def decision(src_scene, tgt_scene, pairs, edges, rejected=None):
    """All pairs accepted except those in ``rejected`` {pair: reason}."""
    rejected = rejected or {}
    return MatchDecision(src_scene, 0, tgt_scene, 0, dict(pairs), edges,
                         [NodeDecision(i, k, (i, k) not in rejected, rejected.get((i, k), "accepted"))
                          for i, k in pairs])


def graph(sid, n, comps):
    return SceneGraph(sid, np.eye(n), np.zeros((0, 2), np.int64), [np.asarray(c) for c in comps])


@pytest.fixture
def two_scenes():
    d1 = decision(0, 1, [(0, 3), (1, 4), (2, 5)], [((0, 1), (3, 4)), ((1, 2), (4, 5))],
                  rejected={(2, 5): "precision_recall"})
    d2 = decision(1, 0, [(5, 0), (6, 7)], [((5, 6), (0, 7))])  # merges 5+6 in scene 1, 0+7 in scene 0
    d3 = decision(0, 1, [(8, 1)], [], rejected={(8, 1): "no_mapped_edge"})
    d4 = decision(0, 1, [(3, 0), (4, 2)], [((3, 4), (0, 2))], rejected={(3, 0): "cost_above_T1",
                                                                       (4, 2): "cost_above_T1"})
    decisions = [d1, d2, d3, d4]
    objects = merge_segments([9, 7], decisions)
    graphs = [graph("A", 9, [[0, 1, 2, 7], [3, 4], [5, 6, 8]]), graph("B", 7, [[0, 1, 2, 3, 4, 5, 6]])]
    stats = {"component_pairs": 6, "prefiltered": 2, "solved": 4, "nonempty": 4, "solver_s": 0.1}
    return diagnostics(["A", "B"], graphs, stats, decisions, objects), objects


def test_diagnostics_counts(two_scenes):
    diag, _ = two_scenes
    assert diag["scenes"]["A"] == {"segments": 9, "components": 3, "objects": 7, "merged_segments": 3, "merges": 2}
    assert diag["scenes"]["B"] == {"segments": 7, "components": 1, "objects": 5, "merged_segments": 4, "merges": 2}
    assert diag["totals"] == {"segments": 16, "components": 4, "merged_segments": 7, "merges": 4}
    assert diag["matching"] == {"component_pairs": 6, "prefiltered": 2, "solved": 4, "nonempty": 4}
    assert diag["pruning"]["decisions"] == 4
    assert diag["pruning"]["matches_by_outcome"] == {"merged": 2, "no_mapped_edge": 1, "cost_above_T1": 1}
    assert diag["pruning"]["node_pairs_by_reason"] == {"accepted": 4, "precision_recall": 1, "no_mapped_edge": 1,
                                                       "cost_above_T1": 2}
    assert diag["merges"]["accepted_edges"] == 2
    assert diag["merges"]["within"] == {"A": [[0, 1], [0, 7]], "B": [[3, 4], [5, 6]]}
    assert diag["merges"]["across"] == [["A", 0, "B", 3], ["A", 1, "B", 4], ["B", 5, "A", 0], ["B", 6, "A", 7]]


def test_merge_precision_recall_known_answers(two_scenes):
    diag, objects = two_scenes
    # GT: scene A segments 0, 1, 7 on instance 1 (obj 10), 2 on instance 1 too, 3..6 instance 2 (obj 20),
    # 8 background; scene B: 3, 4 on instance 5 (obj 10), 5 on instance 6 (obj 30), 6 on 7 (obj 10), rest 0
    seg_inst = {"A": np.array([1, 1, 1, 2, 2, 2, 2, 1, 0]), "B": np.array([0, 0, 0, 5, 5, 6, 7])}
    inst_obj = {"A": {1: 10, 2: 20}, "B": {5: 10, 6: 30, 7: 10}}
    seg_object = {"A": objects[0], "B": objects[1]}
    edges = {"A": np.array([[0, 1], [1, 2], [3, 4], [0, 7], [7, 8]]), "B": np.array([[3, 4], [4, 5], [5, 6]])}
    m = merge_scores(diag, seg_inst, inst_obj, seg_object, edges)
    # within merges: A (0,1) ok, (0,7) ok; B (3,4) ok, (5,6) instances 6 ≠ 7: wrong → 3/4
    # adjacent same-instance pairs: A (0,1) merged, (1,2) not, (3,4) not, (0,7) merged; B (3,4) merged → 3/5
    assert m["within"] == {"merges": 4, "correct": 3, "precision": 0.75, "same_instance_adjacent": 5, "merged": 3,
                           "recall": 0.6}
    # across: A0–B3 (10, 10) ok, A1–B4 ok, B5–A0 (30 vs 10) wrong, B6–A7 (10, 10) ok → 3/4
    # reappearing: obj 10 in both scenes: A 0, 1, 2, 7 and B 3, 4, 6 (7 segments); matched correctly: A 0, 1, 7,
    # B 3, 4, 6 → 6/7
    assert m["across"] == {"pairs": 4, "correct": 3, "precision": 0.75, "reappearing_segments": 7,
                           "matched_segments": 6, "recall": pytest.approx(6 / 7)}


def test_segment_instances_majority():
    seg = np.array([0, 0, 0, 1, 1, -1, 2, 2, 2])
    gt = np.array([3, 3, 1, 0, 0, 3, 2, 0, 2])
    assert segment_instances(seg, gt, 4).tolist() == [3, 0, 2, 0]  # segment 3 has no point


def test_cosine_by_object_known_answers():
    e = np.eye(3)
    feats = {"A": np.array([e[0], e[1], 2 * e[2]]), "B": np.array([e[0], (e[0] + e[1]) / np.sqrt(2)])}
    seg_inst = {"A": np.array([1, 2, 0]), "B": np.array([4, 5])}  # A's third segment is background
    inst_obj = {"A": {1: 7, 2: 8}, "B": {4: 7, 5: 9}}
    c = cosine_by_object(feats, seg_inst, inst_obj)
    # same object: A0–B0 = 1; different: A0–B1 = A1–B1 = 1/√2, A1–B0 = 0
    assert c["same_object"] == summary([1.0])
    assert c["different_object"]["n"] == 3 and c["different_object"]["max"] == pytest.approx(2 ** -0.5)
    assert c["different_object"]["median"] == pytest.approx(2 ** -0.5)
    assert summary([]) == {"n": 0, "q25": None, "median": None, "q75": None, "max": None}


def test_merge_same_instance_known_answers():
    # segments 0, 1 (instance 1) share an edge: merged; 2 (instance 1) touches only 3 (instance 2): kept apart;
    # 4, 5 lie mostly on no object (instance 0): never merged, even along an edge
    groups = merge_same_instance(np.array([[0, 1], [2, 3], [4, 5], [1, 3]]), np.array([1, 1, 1, 2, 0, 0]))
    assert groups[0] == groups[1]
    assert len({groups[i] for i in (0, 2, 3, 4, 5)}) == 5
    # per-point labels follow their segment's group; −1 (no segment) stays −1
    assert relabel(np.array([[1, -1], [5, 0]]), groups).tolist() == [[groups[1], -1], [groups[5], groups[0]]]
    # no edges: every segment its own group
    assert merge_same_instance(np.zeros((0, 2), np.int64), np.array([1, 1, 2])).tolist() == [0, 1, 2]
    # a chain of one instance through three segments merges all three
    assert len(set(merge_same_instance(np.array([[0, 1], [1, 2]]), np.array([7, 7, 7])))) == 1


def test_segment_votes_majority_over_frames():
    from selfseg.baselines.gt_merging import segment_votes

    seg_a = np.array([[0, 0, 1], [1, -1, 2]])
    inst_a = np.array([[3, 3, 0], [5, 5, 0]])
    seg_b = np.array([[1, 1, 1], [2, 2, -1]])
    inst_b = np.array([[5, 5, 5], [0, 0, 4]])
    # segment 0: instance 3 (2 px); segment 1: 0, 5, 5, 5, 5 → 5; segment 2: 0, 0, 0 → 0; segment 3: no pixel → 0
    assert segment_votes([seg_a, seg_b], [inst_a, inst_b], 4).tolist() == [3, 5, 0, 0]
