"""Registration precision/recall and the three pruning criteria, each on a constructed false match."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from selfseg.method.matching import MatchConfig, MatchResult, PairMatch, SceneGraph, match_all, match_graphs
from selfseg.method.pruning import PruneConfig, criterion_cost, criterion_isolation, prune_matches
from selfseg.method.registration import precision_recall, register
from selfseg.poses import invert_T, transform_points


def sample(mesh: trimesh.Trimesh, n: int, seed: int) -> np.ndarray:
    return np.asarray(trimesh.sample.sample_surface(mesh, n, seed=seed)[0])


def l_shape() -> trimesh.Trimesh:
    return trimesh.util.concatenate([
        trimesh.creation.box((0.08, 0.03, 0.03)),
        trimesh.creation.box((0.03, 0.06, 0.03)).apply_translation((0.025, 0.045, 0)),
        trimesh.creation.cylinder(0.012, 0.05).apply_translation((-0.03, 0, 0.04))])


def rigid(seed: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = np.random.default_rng(seed).uniform(-0.3, 0.3, 3)
    return T


def test_registration_recovers_rigid_copy_and_rejects_other_shape():
    cfg = PruneConfig()
    src = sample(l_shape(), 3000, 0)
    T = rigid(1)
    reg = register(src, transform_points(src, T), cfg.reg_voxel_m)
    assert precision_recall(src, transform_points(src, T), reg.T_tgt_src, cfg.dist_thresh_m) == (1.0, 1.0)
    assert np.abs(reg.T_tgt_src - T).max() < 0.01
    other = sample(trimesh.creation.icosphere(radius=0.045), 3000, 0)
    reg = register(src, other, cfg.reg_voxel_m)
    p, r = precision_recall(src, other, reg.T_tgt_src, cfg.dist_thresh_m)
    assert min(p, r) < 0.7


def path_match(cost: float, n: int = 3) -> PairMatch:
    edges = [((t, t + 1), (10 + t, 11 + t)) for t in range(n - 1)]
    res = MatchResult({t: 10 + t for t in range(n)}, edges, cost, "lp_integral", 0.0)
    return PairMatch(0, 0, 1, 0, n, n - 1, res)


def test_criterion_cost_rejects_weak_match():
    rng = np.random.default_rng(0)
    f = rng.normal(size=(3, 16))
    f /= np.linalg.norm(f, axis=1, keepdims=True)

    def at_distance(d):  # unit vectors at cosine distance d from f's rows
        u = rng.normal(size=f.shape)
        u -= (u * f).sum(1, keepdims=True) * f
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        return (1 - d) * f + np.sqrt(1 - (1 - d) ** 2) * u

    path = np.array([[0, 1], [1, 2]])
    weak = match_graphs(f, path, at_distance(0.08), path, MatchConfig())
    strong = match_graphs(f, path, at_distance(0.01), path, MatchConfig())
    assert len(weak.node_map) == len(strong.node_map) == 3
    assert weak.cost == pytest.approx(0.5 - 3 * 0.02 - 0.2)
    wrap = lambda r: PairMatch(0, 0, 1, 0, 3, 2, r)  # noqa: E731
    assert not criterion_cost(wrap(weak), 0.04)[0] and criterion_cost(wrap(strong), 0.04)[0]
    assert criterion_cost(wrap(weak), 0.1)[0]
    # with α = 0.1 = c_del, T1 is the empty match's J: a match that only ties it is rejected
    assert not criterion_cost(path_match(0.5), 0.1)[0]


def unit(rng, n):
    f = rng.normal(size=(n, 16))
    return f / np.linalg.norm(f, axis=1, keepdims=True)


def test_criterion_isolation_drops_superset_match():
    """A mug (body, handle) stands alone in scene 0 and touches the same box in scenes 1 and 2.
    Scenes 1 and 2 match mug+box as a whole; scene 0's isolated mug matches the mug in scene 1,
    so the larger match into scene 1 (which would merge the box into the mug) is dropped."""
    rng = np.random.default_rng(1)
    mug, box = unit(rng, 2), unit(rng, 1)
    noisy = lambda f: f + 0.03 * rng.normal(size=f.shape)  # noqa: E731
    s0 = SceneGraph("0", np.vstack([noisy(mug), unit(rng, 1)]), np.array([[0, 1]]), [np.array([0, 1]), np.array([2])])
    s1 = SceneGraph("1", np.vstack([noisy(mug), noisy(box)]), np.array([[0, 1], [1, 2]]), [np.array([0, 1, 2])])
    s2 = SceneGraph("2", np.vstack([noisy(mug), noisy(box)]), np.array([[0, 1], [1, 2]]), [np.array([0, 1, 2])])
    matches = [m for m in match_all([s0, s1, s2], MatchConfig(workers=1), progress=False) if m.result.node_map]
    find = lambda s, c, t: next(n for n, m in enumerate(matches)  # noqa: E731
                                if (m.src_scene, m.src_comp, m.tgt_scene) == (s, c, t))
    witness, victim = find(0, 0, 1), find(2, 0, 1)
    assert set(matches[victim].result.node_map.values()) == {0, 1, 2}
    dropped = criterion_isolation(matches)
    assert dropped[victim] == witness
    assert find(1, 0, 2) in dropped  # symmetric case: scene 0's mug also isolates scene 2's mug
    assert witness not in dropped and find(1, 0, 0) not in dropped  # mug+box into scene 0 only maps the mug


def test_criterion_registration_rejects_wrong_shape_pair():
    """Features say (L-part, knob) ↔ (L-part, knob), but the target's knob is a flat plate: the
    registered pair (L, L) is merged, the knob pair is rejected on precision/recall."""
    cfg = PruneConfig()
    L = sample(l_shape(), 4000, 0)
    knob = sample(trimesh.creation.icosphere(radius=0.02).apply_translation((-0.07, 0, 0)), 1500, 1)
    plate = sample(trimesh.creation.box((0.005, 0.05, 0.05)).apply_translation((-0.045, 0, 0)), 1500, 2)
    T = rigid(3)
    clouds = {(0, 0): L, (0, 1): knob, (1, 5): transform_points(sample(l_shape(), 4000, 9), T), (1, 6): transform_points(plate, T)}
    f = unit(np.random.default_rng(2), 2)
    r = match_graphs(f, np.array([[0, 1]]), f, np.array([[0, 1]]), MatchConfig())
    r.node_map = {i: k + 5 for i, k in r.node_map.items()}
    r.edge_map = [((0, 1), (5, 6))]
    (d,) = prune_matches([PairMatch(0, 0, 1, 0, 2, 1, r)], lambda s, seg: clouds[(s, seg)], cfg, progress=False)
    pairs = {p.src: p for p in d.pairs}
    assert pairs[0].accepted and pairs[0].precision >= 0.9 and pairs[0].recall >= 0.9
    assert not pairs[1].accepted and pairs[1].reason == "precision_recall"
    assert d.accepted_edges() == []  # so nothing gets merged


def test_witness_threshold_separates_merging_from_isolation():
    """An isolated L-shape (one segment) in scene 0 registers onto half of the target's L (P 1, R ≈ .5),
    which contains L + knob as two segments. At T2 0 that pair merges; it witnesses criterion 3 only if
    the witness threshold lets a half-covered pair through, and then it vetoes the L + knob match."""
    cfg0 = PruneConfig(pr_thresh=0.0)
    L = sample(l_shape(), 4000, 0)
    half = L[L[:, 0] < 0]
    knob = sample(trimesh.creation.icosphere(radius=0.02).apply_translation((-0.09, 0, 0)), 1500, 1)
    T = rigid(4)
    clouds = {(0, 0): transform_points(half, invert_T(T)), (1, 5): L, (1, 6): knob,
              (2, 0): transform_points(L, T), (2, 1): transform_points(knob, T)}
    whole = PairMatch(0, 0, 1, 0, 1, 0, MatchResult({0: 5}, [], 0.0, "lp_integral", 0.0))
    pair = PairMatch(2, 0, 1, 0, 2, 1, MatchResult({0: 5, 1: 6}, [((0, 1), (5, 6))], 0.0, "lp_integral", 0.0))
    get = lambda s, seg: clouds[(s, seg)]  # noqa: E731
    d_whole, d_pair = prune_matches([whole, pair], get, cfg0, progress=False)
    (p,) = d_whole.pairs
    assert p.accepted and p.precision > 0.9 and p.recall < 0.7
    assert d_pair.isolation_witness == 0 and d_pair.accepted_edges() == []
    for wt in (0.7, 0.9):
        d_whole, d_pair = prune_matches([whole, pair], get, PruneConfig(pr_thresh=0.0, witness_pr_thresh=wt),
                                        progress=False)
        assert d_whole.pairs[0].accepted and d_pair.isolation_witness is None
        assert d_pair.accepted_edges() == [((0, 1), (5, 6))]


def test_isolation_cover_spares_the_witnessed_objects_other_parts():
    """Scene 0 sees an L-shape whole, as one isolated segment; scene 1 splits it into halves 5 and 6 and
    joins a knob 7 to it. Scene 0's L matches half 5 only and so witnesses criterion 3. Scene 2's match
    onto both halves (5, 6) is the same object split differently: with ``isolation_cover`` it survives, since
    the registered whole L covers half 6; its match onto (5, knob 7) is dropped either way."""
    L = sample(l_shape(), 4000, 0)
    a, b = L[L[:, 0] < 0], L[L[:, 0] >= 0]
    knob = sample(trimesh.creation.icosphere(radius=0.02).apply_translation((-0.09, 0, 0)), 1500, 1)
    T0, T2 = rigid(6), rigid(7)  # rigid(5) registers the whole L onto the wrong place on half 5 (ambiguous)
    clouds = {(0, 0): transform_points(L, T0), (1, 5): a, (1, 6): b, (1, 7): knob,
              (2, 0): transform_points(a, T2), (2, 1): transform_points(b, T2), (2, 2): transform_points(knob, T2)}
    res = lambda nm, e: MatchResult(nm, e, 0.0, "lp_integral", 0.0)  # noqa: E731
    matches = [PairMatch(0, 0, 1, 0, 1, 0, res({0: 5}, [])),
               PairMatch(2, 0, 1, 0, 2, 1, res({0: 5, 1: 6}, [((0, 1), (5, 6))])),
               PairMatch(2, 1, 1, 0, 2, 1, res({0: 5, 2: 7}, [((0, 2), (5, 7))]))]
    get = lambda s, seg: clouds[(s, seg)]  # noqa: E731
    paper = prune_matches(matches, get, PruneConfig(pr_thresh=0.0), progress=False)
    assert [d.isolation_witness for d in paper] == [None, 0, 0]
    cover = prune_matches(matches, get, PruneConfig(pr_thresh=0.0, isolation_cover=0.5), progress=False)
    assert [d.isolation_witness for d in cover] == [None, None, 0]
    assert cover[1].accepted_edges() == [((0, 1), (5, 6))] and cover[2].accepted_edges() == []
