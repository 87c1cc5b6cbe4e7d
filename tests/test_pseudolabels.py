"""Pseudo-labels end to end on two small point-cloud scenes, in the three modes, and the merge rule."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from selfseg.fileio import read_json
from selfseg.method.pruning import MatchDecision, NodeDecision
from selfseg.method.pseudolabels import PseudoLabelConfig, SceneData, make_pseudo_labels, merge_segments
from selfseg.method.segment_graph import build_segment_graph
from selfseg.poses import transform_points

# a three-part object: box, bar and ball in a row, touching
OBJECT = [trimesh.creation.box((0.06, 0.04, 0.03)),
          trimesh.creation.cylinder(0.01, 0.08, transform=trimesh.transformations.rotation_matrix(
              np.pi / 2, (0, 1, 0))).apply_translation((0.07, 0, 0)),
          trimesh.creation.icosphere(radius=0.025).apply_translation((0.135, 0, 0))]


def pose(seed: int, at) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", np.random.default_rng(seed).uniform(0, 2 * np.pi)).as_matrix()
    T[:3, 3] = at
    return T


def unit(rng, n):
    f = rng.normal(size=(n, 16))
    return f / np.linalg.norm(f, axis=1, keepdims=True)


def make_scene(scene_id, parts, feats, seed):
    """parts: list of (mesh, 4×4 pose); features given per part. Segment ids are shuffled."""
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(parts))  # segment id of part p is order[p]
    pts, lab = [], []
    for p, (mesh, T) in enumerate(parts):
        x = np.asarray(trimesh.sample.sample_surface(mesh, 1500, seed=seed + p)[0])
        pts.append(transform_points(x, T))
        lab.append(np.full(len(x), order[p]))
    pts.append(rng.uniform(2, 3, size=(10, 3)))  # a few points in no segment
    lab.append(np.full(10, -1))
    points, labels = np.vstack(pts), np.concatenate(lab).astype(np.int32)
    graph = build_segment_graph(points, labels)
    f = np.empty((len(parts), 16))
    f[order] = feats + 0.03 * rng.normal(size=feats.shape)
    return SceneData(scene_id, points, graph, f / np.linalg.norm(f, axis=1, keepdims=True)), order


@pytest.fixture(scope="module")
def scenes():
    rng = np.random.default_rng(0)
    proto = unit(rng, 3)
    TA, TB = pose(1, (0, 0, 0)), pose(2, (0.5, 0.5, 0))
    far = lambda x: pose(9, (x, -0.6, 0))  # noqa: E731
    # scene A: the object, a ball touching its box (same component), a lone box
    touching = trimesh.creation.icosphere(radius=0.02).apply_translation((0, 0.04, 0))
    a_parts = [(m, TA) for m in OBJECT] + [(touching, TA), (trimesh.creation.box((0.05, 0.05, 0.05)), far(0.0))]
    a, oa = make_scene("A", a_parts, np.vstack([proto, unit(rng, 2)]), 10)
    # scene B: the object alone, a lone cylinder, and a lure: a thin rod whose feature looks like the box part
    b_parts = [(m, TB) for m in OBJECT] + [(trimesh.creation.cylinder(0.02, 0.06), far(0.3)),
                                           (trimesh.creation.cylinder(0.008, 0.12), far(0.6))]
    b, ob = make_scene("B", b_parts, np.vstack([proto, unit(rng, 1), proto[:1]]), 20)
    return [a, b], [oa, ob]


def part_labels(scene: SceneData, labels: np.ndarray, order) -> list[int]:
    """The pseudo-label of each part (all its points must agree)."""
    out = []
    for p in range(len(order)):
        vals = np.unique(labels[scene.graph.labels == order[p]])
        assert len(vals) == 1
        out.append(int(vals[0]))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["ours", "v3_no_pruning", "v4_registration_only"])
def test_pseudo_labels_merge_the_object_only(scenes, mode, tmp_path):
    data, orders = scenes
    labels = make_pseudo_labels(data, PseudoLabelConfig(mode=mode), tmp_path, progress=False)
    for scene, order in zip(data, orders):
        lab = labels[scene.scene_id]
        assert lab.dtype == np.int32 and lab.shape == (len(scene.points_w),)
        assert (lab[scene.graph.labels < 0] == -1).all()
        parts = part_labels(scene, lab, order)
        assert parts[0] == parts[1] == parts[2]  # the object's three segments are one object
        assert len(set(parts[2:])) == len(parts) - 2  # every distractor keeps its own label
    record = read_json(tmp_path / "matches.json")
    # the object's two edges, merged in both directions (V4 registers each component pair once)
    assert record["mode"] == mode and record["n_merged_edges"] >= (2 if mode.startswith("v4") else 4)
    assert all(p["reason"] for m in record["matches"] for p in m["pairs"])
    diag = read_json(tmp_path / "diagnostics.json")
    # each scene: 5 segments, the object's 3 merged by 2 unions; A: object + touching ball, lone box
    assert diag["scenes"]["A"] == {"segments": 5, "components": 2, "objects": 3, "merged_segments": 3, "merges": 2}
    assert diag["scenes"]["B"] == {"segments": 5, "components": 3, "objects": 3, "merged_segments": 3, "merges": 2}
    object_pairs = {("A", int(orders[0][p]), "B", int(orders[1][p])) for p in range(3)}
    across = {tuple(x) if x[0] == "A" else (x[2], x[3], x[0], x[1]) for x in diag["merges"]["across"]}
    assert across == object_pairs  # the object's parts, each matched to itself
    if mode == "ours":  # the object merged both ways; the lure pruned by registration, its lone pair unregistered
        assert diag["matching"]["nonempty"] == diag["pruning"]["decisions"] == 4
        assert diag["pruning"]["matches_by_outcome"] == {"merged": 2, "no_mapped_edge": 1, "precision_recall": 1}
    if mode == "ours":  # the lure (a rod with the box part's feature) was matched, then pruned
        lure = int(orders[1][4])
        pairs = [(m, p) for m in record["matches"] for p in m["pairs"]]
        as_src = {p["reason"] for m, p in pairs if m["src_scene"] == "B" and p["src"] == lure}
        as_tgt = {p["reason"] for m, p in pairs if m["tgt_scene"] == "B" and p["tgt"] == lure}
        assert as_src == {"precision_recall"}  # a whole (isolated) component: registered, rejected
        assert as_tgt == {"no_mapped_edge"}  # a lone node pair could merge nothing: not registered

@pytest.mark.slow
def test_runs_that_differ_after_matching_match_once(scenes, tmp_path, monkeypatch):
    """ours fills the match cache; V3 with the same graphs and MatchConfig reads it (match_all is not called) and
    gives what V3 gives matching itself; another MatchConfig is another entry."""
    from selfseg.method import pseudolabels
    from selfseg.method.matching import MatchConfig

    data, _ = scenes
    cache = tmp_path / "cache"
    make_pseudo_labels(data, PseudoLabelConfig(mode="ours"), tmp_path / "ours", progress=False, match_cache=cache)
    assert len(list(cache.glob("matches-*.json"))) == 1
    assert read_json(tmp_path / "ours/diagnostics.json")["matching_from_cache"] is False
    alone = make_pseudo_labels(data, PseudoLabelConfig(mode="v3_no_pruning"), tmp_path / "alone", progress=False)

    def no_matching(*args, **kwargs):
        raise AssertionError("match_all ran although the cache holds this matching")

    with monkeypatch.context() as m:
        m.setattr(pseudolabels, "match_all", no_matching)
        cached = make_pseudo_labels(data, PseudoLabelConfig(mode="v3_no_pruning"), tmp_path / "v3", progress=False,
                                    match_cache=cache)
        with pytest.raises(AssertionError, match="match_all ran"):  # other costs: not in the cache
            make_pseudo_labels(data, PseudoLabelConfig(mode="v3_no_pruning", match=MatchConfig(c_del_node=0.2)),
                               tmp_path / "other", progress=False, match_cache=cache)
    assert read_json(tmp_path / "v3/diagnostics.json")["matching_from_cache"] is True
    assert {k: v.tolist() for k, v in cached.items()} == {k: v.tolist() for k, v in alone.items()}
    strip = lambda r: {k: v for k, v in r.items() if k != "match_stats"}  # noqa: E731 (timings differ)
    assert strip(read_json(tmp_path / "v3/matches.json")) == strip(read_json(tmp_path / "alone/matches.json"))


def decision(src_scene, tgt_scene, pairs, edges, rejected=()):
    return MatchDecision(src_scene, 0, tgt_scene, 0, dict(pairs), edges,
                         [NodeDecision(i, k, (i, k) not in rejected, "test") for i, k in pairs])


def test_merge_follows_accepted_edges_only():
    d1 = decision(0, 1, [(0, 3), (1, 4), (2, 5)], [((0, 1), (3, 4)), ((1, 2), (4, 5))], rejected={(2, 5)})
    d2 = decision(1, 0, [(5, 0), (6, 7)], [((5, 6), (0, 7))])  # merges 5+6 in scene 1, 0+7 in scene 0
    d3 = decision(0, 1, [(8, 1)], [])  # a lone matched pair merges nothing
    obj0, obj1 = merge_segments([9, 7], [d1, d2, d3])
    groups = lambda obj: sorted(sorted(np.nonzero(obj == o)[0].tolist()) for o in np.unique(obj))  # noqa: E731
    assert groups(obj0) == [[0, 1, 7], [2], [3], [4], [5], [6], [8]]
    assert groups(obj1) == [[0], [1], [2], [3, 4], [5, 6]]
    assert obj0[0] == 0 and obj0.max() == 6  # renumbered by smallest segment id


def test_v4_registers_only_component_pairs_with_a_node_pair_at_the_cosine_threshold(monkeypatch):
    """V4 accepts node pairs at cos ≥ cos_thresh only, so a component pair without one is not registered;
    one with one is registered and its pair accepted (the same box in both scenes, moved)."""
    from selfseg.method import pseudolabels

    calls = []
    real = pseudolabels.register_clouds
    monkeypatch.setattr(pseudolabels, "register_clouds", lambda *a: calls.append(1) or real(*a))
    box = trimesh.creation.box((0.08, 0.05, 0.04)).sample(600, seed=0)
    moved = transform_points(box, pose(1, (0.1, 0.0, 0.0)))
    cfg = PseudoLabelConfig(mode="v4_registration_only")
    edges = np.zeros((0, 2), np.int64)
    f = np.eye(4)[:1]
    args = (0, 0, 1, 0, np.array([0]), np.array([0]), {0: box}, {0: moved})
    assert pseudolabels._v4_component_pair(*args, f, np.eye(4)[1:2], edges, edges, cfg) is None
    assert calls == []
    d = pseudolabels._v4_component_pair(*args, f, f, edges, edges, cfg)
    assert len(calls) == 1 and d is not None and [(p.src, p.tgt, p.accepted) for p in d.pairs] == [(0, 0, True)]


def test_a_run_needing_a_matching_being_computed_waits_and_reads_it(tmp_path, capfd):
    """While another process holds a match cache entry's lock (computing it), a run that needs the same matching
    waits, then reads what that process wrote: it does not solve it a second time."""
    import itertools
    import threading

    from selfseg.fileio import exclusive_lock, write_json
    from selfseg.method.matching import MatchConfig, SceneGraph, match_all
    from selfseg.method.pseudolabels import MATCH_CACHE_JSON, MATCH_CACHE_LOCK, cached_match_all, match_key

    graphs = [SceneGraph(n, np.eye(3, 4) + k, np.array(list(itertools.combinations(range(3), 2))), [np.arange(3)])
              for k, n in enumerate("ab")]
    cfg = MatchConfig(workers=1)
    key = match_key(graphs, cfg)
    cache = tmp_path / "cache"
    got = {}
    with exclusive_lock(cache / MATCH_CACHE_LOCK.format(key_hash=key), "the test"):
        waiter = threading.Thread(target=lambda: got.update(r=cached_match_all(graphs, cfg, cache, None, False)))
        waiter.start()
        for _ in range(200):  # until the waiter says it waits (it found the entry missing and the lock held)
            if "waiting for it" in capfd.readouterr().err:
                break
            waiter.join(0.05)
        else:
            pytest.fail("the run did not wait for the lock's holder")
        assert waiter.is_alive()
        matches = match_all(graphs, cfg, None, False)
        write_json(cache / MATCH_CACHE_JSON.format(key_hash=key),
                   {"config": {}, "scenes": ["a", "b"], "matches": [m.to_json() for m in matches]})
    waiter.join(60)
    read, from_cache = got["r"]
    assert from_cache is True
    assert [m.to_json() for m in read] == [m.to_json() for m in matches]
