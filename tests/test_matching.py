"""Graph matching: optimality against brute force, pre-filter soundness, planted patterns."""
from __future__ import annotations

import concurrent.futures as cf
import itertools
import json
import os
from concurrent.futures.process import BrokenProcessPool

import numpy as np
import pytest

from selfseg.method import matching
from selfseg.method.matching import (MatchBudgetError, MatchConfig, PairMatch, SceneGraph, cosine_distance,
                                     empty_match_cost, match_all, match_batch, match_costs, match_graphs,
                                     match_stats, prefilter)


def brute_force(C: np.ndarray, e1: np.ndarray, e2: np.ndarray, cfg: MatchConfig) -> float:
    """Minimum J over every injective partial node map, with every possible edge mapped.

    For a fixed node map f the best edge assignment maps exactly the source edges ij whose
    image (f(i), f(j)) is a target edge (each has cost −c_del_edge < 0).
    """
    n1, n2 = C.shape
    A2 = np.zeros((n2, n2), dtype=bool)
    A2[e2[:, 0], e2[:, 1]] = A2[e2[:, 1], e2[:, 0]] = True
    best = empty_match_cost(n1, len(e1), cfg)
    for r in range(1, min(n1, n2) + 1):
        perms = np.array(list(itertools.permutations(range(n2), r)))
        for S in itertools.combinations(range(n1), r):
            pos = {v: t for t, v in enumerate(S)}
            cost = C[list(S)][np.arange(r), perms].sum(axis=1) - cfg.c_del_node * r
            for i, j in e1:
                if i in pos and j in pos:
                    cost = cost - cfg.c_del_edge * A2[perms[:, pos[i]], perms[:, pos[j]]]
            best = min(best, empty_match_cost(n1, len(e1), cfg) + cost.min())
    return float(best)


def check_consistent(r, C, e1, e2, cfg):
    """The returned maps are a valid match whose cost is r.cost."""
    assert len(set(r.node_map.values())) == len(r.node_map)
    E1 = {tuple(sorted(e)) for e in e1.tolist()}
    E2 = {tuple(sorted(e)) for e in e2.tolist()}
    for (i, j), (k, l) in r.edge_map:
        assert (i, j) in E1 and tuple(sorted((k, l))) in E2
        assert r.node_map[i] == k and r.node_map[j] == l
    # every source edge whose image is a target edge is mapped (optimality of y given x)
    mapped = {(i, j) for (i, j), _ in r.edge_map}
    for i, j in E1:
        if i in r.node_map and j in r.node_map and tuple(sorted((r.node_map[i], r.node_map[j]))) in E2:
            assert (i, j) in mapped
    cost = (empty_match_cost(len(C), len(e1), cfg) + sum(C[i, k] - cfg.c_del_node for i, k in r.node_map.items())
            - cfg.c_del_edge * len(r.edge_map))
    assert r.cost == pytest.approx(cost, abs=1e-9)


def random_edges(rng, n, p):
    e = [(i, j) for i in range(n) for j in range(i + 1, n) if rng.random() < p]
    return np.array(e, dtype=np.int64).reshape(-1, 2)


def random_instance(rng, n1, n2, spread=0.35):
    """Costs concentrated near the deletion cost, so edges decide and ties are common."""
    C = rng.uniform(0.0, spread, size=(n1, n2))
    if rng.random() < 0.3:
        C = np.round(C, 1)  # exact ties
    return C, random_edges(rng, n1, rng.uniform(0.2, 0.7)), random_edges(rng, n2, rng.uniform(0.2, 0.7))


CONFIGS = [MatchConfig(), MatchConfig(lp_first=False), MatchConfig(prefilter=False)]


def test_optimal_matches_brute_force():
    """J equals brute force with the default pipeline and, in turn, with the MILP alone and
    without the pre-filter."""
    rng = np.random.default_rng(1)
    sizes = [(6, 8)] * 4 + [(int(rng.integers(1, 7)), int(rng.integers(1, 9))) for _ in range(26)]
    n_nonempty = 0
    for n, (n1, n2) in enumerate(sizes):
        C, e1, e2 = random_instance(rng, n1, n2)
        opt = brute_force(C, e1, e2, MatchConfig())
        for cfg in (CONFIGS[0], CONFIGS[1 + n % 2]):
            r = match_costs(C, e1, e2, cfg)
            assert r.status != "time_limit"
            assert r.cost == pytest.approx(opt, abs=1e-6), (n1, n2, cfg)
            check_consistent(r, C, e1, e2, cfg)
        n_nonempty += opt < empty_match_cost(n1, len(e1), MatchConfig()) - 1e-9
    assert n_nonempty >= 15  # the instances are not trivially empty


def test_stacked_batch_is_optimal_per_block():
    rng = np.random.default_rng(2)
    problems = [random_instance(rng, 4, 6) for _ in range(10)]
    cfg = MatchConfig()
    batch = match_batch(problems, cfg)
    for (C, e1, e2), r in zip(problems, batch):
        assert r.cost == pytest.approx(brute_force(C, e1, e2, cfg), abs=1e-6)
        check_consistent(r, C, e1, e2, cfg)


def test_prefilter_is_sound():
    """Whenever the pre-filter (bound + reduction) declares the empty match optimal, brute
    force finds nothing better; and the bound does fire on a good share of instances."""
    rng = np.random.default_rng(3)
    hits = misses = 0
    for _ in range(300):
        n1, n2 = int(rng.integers(2, 6)), int(rng.integers(2, 8))
        C, e1, e2 = random_instance(rng, n1, n2, spread=rng.uniform(0.1, 0.6))
        C = C + rng.uniform(0.0, 0.2)  # move the instance across the pre-filter threshold
        empty, _ = prefilter(C, e1, e2, MatchConfig())
        if empty:
            hits += 1
            assert brute_force(C, e1, e2, MatchConfig()) >= empty_match_cost(n1, len(e1), MatchConfig()) - 1e-12
        else:
            misses += 1
    assert hits >= 60 and misses >= 60


def test_reduction_keeps_optimum_reachable():
    """The pairs kept by the reduction still contain an optimal match (brute force restricted
    to kept pairs equals the unrestricted optimum)."""
    rng = np.random.default_rng(6)
    checked = reduced = 0
    for _ in range(60):
        C, e1, e2 = random_instance(rng, int(rng.integers(2, 6)), int(rng.integers(2, 8)))
        empty, keep = prefilter(C, e1, e2, MatchConfig())
        if empty:
            continue
        checked += 1
        restricted = np.where(keep, C, 1e3)  # forbidding a pair: its substitution never pays
        assert brute_force(restricted, e1, e2, MatchConfig()) == pytest.approx(brute_force(C, e1, e2, MatchConfig()))
        reduced += not keep.all()
    assert checked >= 20 and reduced >= 10


def test_time_limit_is_reported_for_the_hard_block_only():
    # complete graphs with identical features: many symmetric optima, fractional LP
    hard = (np.full((9, 12), 0.05), np.array(list(itertools.combinations(range(9), 2))),
            np.array(list(itertools.combinations(range(12), 2))))
    rng = np.random.default_rng(7)
    easy = next(p for p in (random_instance(rng, 4, 6) for _ in range(200))
                if match_costs(*p, MatchConfig()).status == "milp_optimal")  # small, fractional LP
    # the hard block runs past 10 s unlimited; the easy one solves in ~10 ms, so 1 s leaves it 100× headroom
    r_hard, r_easy = match_batch([hard, easy], MatchConfig(time_limit_s=1.0))
    assert r_hard.status == "time_limit" and not r_hard.proven_optimal
    assert r_easy.status == "milp_optimal" and r_easy.cost == pytest.approx(brute_force(*easy, MatchConfig()))


def test_node_limit_stops_a_milp_the_same_way_on_any_machine(monkeypatch):
    # complete graphs, identical features: a fractional LP whose MILP needs 2 branch-and-bound nodes
    inst = (np.full((5, 6), 0.05), np.array(list(itertools.combinations(range(5), 2))),
            np.array(list(itertools.combinations(range(6), 2))))
    free = match_costs(*inst, MatchConfig())
    assert free.status == "milp_optimal" and free.milp_nodes >= 2
    assert free.cost == pytest.approx(brute_force(*inst, MatchConfig()))
    # the node limit, not the clock, stops it: a generous time limit changes nothing
    stopped = [match_costs(*inst, MatchConfig(node_limit=1, time_limit_s=600.0)) for _ in range(2)]
    assert all(r.status == "time_limit" and not r.proven_optimal for r in stopped)
    # the same match each time: HiGHS's incumbent at 1 node (J .35, not optimal), taken to the optimum by the
    # local search that follows a stopped solve; only the branch and bound could prove it optimal. Its bound
    # brackets the optimum, and the gap (here 0) says how much of the most a match can gain it may miss
    cfg = MatchConfig(node_limit=1)
    assert stopped[0].cost == stopped[1].cost == pytest.approx(free.cost)
    assert stopped[0].cost_bound <= free.cost + 1e-9 and free.cost_bound is None
    assert stopped[0].limit_gap(5, 10, cfg) == 0.0 == free.limit_gap(5, 10, cfg)
    # without the local search the incumbent is .1 above the optimum: a gap of .1 / (J_empty − bound)
    monkeypatch.setattr(matching, "improve_match", lambda z, p, cfg: z)
    raw = match_costs(*inst, MatchConfig(node_limit=1, time_limit_s=600.0))
    gap = raw.limit_gap(5, 10, cfg)
    assert raw.cost == pytest.approx(free.cost + 0.1) and 0 < gap <= 1
    assert gap == pytest.approx((raw.cost - raw.cost_bound) / (empty_match_cost(5, 10, cfg) - raw.cost_bound))
    stats = match_stats([PairMatch(0, 0, 1, 0, 5, 10, r) for r in (free, raw, stopped[0])], cfg)
    assert stats["limit_gap_max"] == pytest.approx(gap) and stats["limit_gap_median"] == pytest.approx(gap / 2)
    # HiGHS stops when its node count reaches the limit, so a solve of n nodes needs a limit of n + 1
    enough = match_costs(*inst, MatchConfig(node_limit=free.milp_nodes + 1))
    assert enough.status == "milp_optimal" and enough.cost == pytest.approx(free.cost)
    stats = match_stats([PairMatch(0, 0, 1, 0, 5, 10, r) for r in (free, enough)], MatchConfig())
    assert stats["milp_nodes_max"] == free.milp_nodes and stats["limit_gap_max"] is None


def unit(rng, n, d=16):
    f = rng.normal(size=(n, d))
    return f / np.linalg.norm(f, axis=1, keepdims=True)


def planted_scene(rng, pattern, n_distract, lure=None):
    """Pattern nodes (3, with noise) first, then distractors wired to them and to each other."""
    f = pattern + 0.05 * rng.normal(size=pattern.shape)
    distract = unit(rng, n_distract)
    if lure is not None:  # a distractor that looks like pattern node 0 but sits elsewhere
        distract[0] = lure + 0.05 * rng.normal(size=lure.shape)
    feats = np.vstack([f, distract])
    edges = [(0, 1), (1, 2)]
    edges += [(3 + d, int(rng.integers(0, 3 + d))) for d in range(n_distract)]  # keeps it connected
    edges = np.unique(np.sort(np.array(edges), axis=1), axis=0)
    return feats, edges


def test_planted_pattern_is_found_and_distractors_are_not():
    rng = np.random.default_rng(4)
    pattern = unit(rng, 3)
    fa, ea = planted_scene(rng, pattern, 6)
    fb, eb = planted_scene(rng, pattern, 9, lure=pattern[0])
    perm = rng.permutation(len(fb))  # shuffle node ids of the target
    inv = np.argsort(perm)
    fb, eb = fb[perm], np.sort(inv[eb], axis=1)
    r = match_graphs(fa, ea, fb, eb, MatchConfig())
    assert r.node_map == {0: int(inv[0]), 1: int(inv[1]), 2: int(inv[2])}
    assert len(r.edge_map) == 2
    assert r.cost < 0.1 * (len(fa) + len(ea))


def test_match_all_every_component_pair_both_directions():
    rng = np.random.default_rng(5)
    pattern = unit(rng, 3)
    scenes, planted = [], []
    for s in range(3):
        fa, ea = planted_scene(rng, pattern, 4)
        other = unit(rng, 3)  # a second component: a path of unrelated nodes
        feats = np.vstack([fa, other])
        edges = np.vstack([ea, [[7, 8], [8, 9]]])
        comps = [np.arange(7), np.arange(7, 10)]
        order = rng.permutation(10)  # global ids differ from component order
        inv = np.argsort(order)
        planted.append(inv[:3])
        scenes.append(SceneGraph(f"s{s}", feats[order], np.sort(inv[edges], axis=1),
                                 [np.sort(inv[c]) for c in comps]))
    cfg = MatchConfig(workers=1)
    serial = match_all(scenes, cfg, progress=False)
    with cf.ThreadPoolExecutor(2) as ex:
        pooled = match_all(scenes, MatchConfig(pairs_per_task=1), executor=ex, progress=False)
    assert len(serial) == 3 * 2 * 2 * 2  # ordered scene pairs × component pairs
    assert {(m.src_scene, m.src_comp, m.tgt_scene, m.tgt_comp) for m in serial} == {
        (a, i, b, j) for a in range(3) for b in range(3) if a != b for i in range(2) for j in range(2)}
    assert [m.result.node_map for m in serial] == [m.result.node_map for m in pooled]
    for m in serial:
        src, tgt = scenes[m.src_scene], scenes[m.tgt_scene]
        if m.src_comp == 0 and m.tgt_comp == 0:  # the planted pattern, in global ids
            for t in range(3):
                assert m.result.node_map[int(planted[m.src_scene][t])] == int(planted[m.tgt_scene][t])
        else:  # unrelated random features
            assert m.result.node_map == {}
        for i, k in m.result.node_map.items():
            assert i in src.components[m.src_comp] and k in tgt.components[m.tgt_comp]
    stats = match_stats(serial, MatchConfig())
    assert stats["component_pairs"] == 24 and stats["time_limit_hits"] == 0 and stats["cpu_s"] > 0
    # a PairMatch written as JSON reads back equal (the match cache's round trip)
    assert [PairMatch.from_json(json.loads(json.dumps(m.to_json()))) for m in serial] == serial
    # a CPU budget it stays within changes nothing (its tasks then run in a budget-limited pool)
    budgeted = match_all(scenes, MatchConfig(workers=1, cpu_budget_per_pair_s=600.0), progress=False)
    assert [m.result.node_map for m in budgeted] == [m.result.node_map for m in serial]


def clique_scene(name: str, n: int) -> SceneGraph:
    """n segments with one feature, all touching: a fractional LP and a MILP of many symmetric optima."""
    return SceneGraph(name, np.ones((n, 4)), np.array(list(itertools.combinations(range(n), 2))), [np.arange(n)])


def test_a_cpu_budget_stops_matching_by_cpu_seconds_not_by_the_clock():
    # matching 9 against 12 touching segments takes about 40 CPU-s; the kernel stops its worker at 1 CPU-s
    with pytest.raises(MatchBudgetError, match="CPU budget of 1 s"):
        match_all([clique_scene("a", 9), clique_scene("b", 12)], MatchConfig(workers=1, cpu_budget_per_pair_s=1.0),
                  progress=False)
    # tasks that finish are counted as they finish: six easy scene pairs, one per task, past a tiny budget
    easy = [clique_scene(f"s{k}", 3) for k in range(4)]
    with cf.ThreadPoolExecutor(1) as ex, pytest.raises(MatchBudgetError, match="scene pairs done"):
        match_all(easy, MatchConfig(pairs_per_task=1, cpu_budget_per_pair_s=1e-9), executor=ex, progress=False)


def _worker_dies(*args):
    os._exit(3)


def test_a_worker_that_dies_for_another_reason_is_not_called_over_budget(monkeypatch):
    # the budget's error needs the kernel's CPU signal (SIGXCPU) as the worker's end; any other end is named
    monkeypatch.setattr(matching, "_match_scene_pairs", _worker_dies)
    with pytest.raises(BrokenProcessPool, match=r"exit codes \[3\]"):
        match_all([clique_scene("a", 3), clique_scene("b", 3)], MatchConfig(workers=1, cpu_budget_per_pair_s=60.0),
                  progress=False)


def test_a_segment_no_frame_saw_is_matched_to_nothing():
    """A zero feature row (a segment φ1's feature frames never saw) is at distance 2 from everything, so the
    match of a graph holding one maps every other node as before and never that one."""
    rng = np.random.default_rng(11)
    f = rng.normal(size=(4, 16))
    f /= np.linalg.norm(f, axis=1, keepdims=True)
    edges = np.array([[0, 1], [1, 2], [2, 3]])
    seen = match_graphs(f, edges, f, edges, MatchConfig())
    assert seen.node_map == {0: 0, 1: 1, 2: 2, 3: 3}
    blind = f.copy()
    blind[2] = 0.0
    d = cosine_distance(blind, f)
    assert (d[2] == 2.0).all() and np.allclose(np.delete(d, 2, axis=0), np.delete(cosine_distance(f, f), 2, axis=0))
    r = match_graphs(blind, edges, f, edges, MatchConfig())
    assert 2 not in r.node_map and r.node_map == {0: 0, 1: 1, 3: 3}


def _j_of(f: np.ndarray, C, e1, e2, cfg) -> float:
    """J of the node map f (−1: unmapped) with every source edge mapped whose image is a target edge."""
    E2 = {tuple(sorted(e)) for e in e2.tolist()}
    mapped = sum(f[i] >= 0 and f[j] >= 0 and tuple(sorted((f[i], f[j]))) in E2 for i, j in e1.tolist())
    return (empty_match_cost(len(C), len(e1), cfg) + sum(C[i, f[i]] - cfg.c_del_node for i in np.nonzero(f >= 0)[0])
            - cfg.c_del_edge * mapped)


def test_local_search_ends_where_no_single_move_helps():
    """From the empty match and from a random map: a feasible solution of the BLP, no worse than where it started,
    whose J is its node map's, and which no single move (map, move, unmap, exchange two targets) improves."""
    rng = np.random.default_rng(11)
    cfg = MatchConfig(prefilter=False)
    n_moved = 0
    for _ in range(12):
        C, e1, e2 = random_instance(rng, int(rng.integers(3, 7)), int(rng.integers(3, 8)))
        n1, n2 = C.shape
        p = matching._prepare(C, e1, e2, cfg)
        start = np.full(n1, -1)
        take = rng.permutation(n2)[:min(n1, n2)]
        start[:len(take)] = np.where(rng.random(len(take)) < 0.6, take, -1)
        for f0 in (np.full(n1, -1), start):
            z0 = matching._encode(f0, p)
            z = matching.improve_match(z0, p, cfg)
            c, (rows, cols, vals), b = p.c, p.A, p.b
            assert np.all(np.bincount(rows, weights=vals * z[cols], minlength=len(b)) <= b + 1e-9)
            node_map, _, j = matching._decode(z, p, cfg)
            f = np.full(n1, -1)
            f[list(node_map)] = list(node_map.values())
            assert j == pytest.approx(_j_of(f, C, e1, e2, cfg)) and j <= _j_of(f0, C, e1, e2, cfg) + 1e-9
            assert j >= brute_force(C, e1, e2, cfg) - 1e-9
            n_moved += not np.array_equal(f, f0)
            for i in range(n1):
                for k in [-1, *range(n2)]:
                    g = f.copy()
                    if k >= 0 and k in f:
                        g[int(np.nonzero(f == k)[0][0])] = f[i]
                    g[i] = k
                    assert _j_of(g, C, e1, e2, cfg) >= j - 1e-9, (f, g)
    assert n_moved >= 12  # the search moved from most starts


def test_a_stack_past_its_node_limit_is_solved_block_by_block():
    """Two clique pairs whose MILPs need branching: stacked under a 1-node stack limit they are re-solved one by one,
    each to its optimum with its own node count; with room the stack solves them together."""
    inst = (np.full((5, 6), 0.05), np.array(list(itertools.combinations(range(5), 2))),
            np.array(list(itertools.combinations(range(6), 2))))
    alone = match_costs(*inst, MatchConfig())
    split = match_batch([inst, inst], MatchConfig(stack_node_limit=1))
    together = match_batch([inst, inst], MatchConfig(stack_node_limit=1000))
    for r in (*split, *together):
        assert r.status == "milp_optimal" and r.cost == pytest.approx(alone.cost)
    assert [r.milp_nodes for r in split] == [alone.milp_nodes] * 2
    assert together[0].milp_nodes == together[1].milp_nodes > alone.milp_nodes  # one search over both blocks
