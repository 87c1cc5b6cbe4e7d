"""Object pseudo-labels from cross-scene matching (paper step 7) and the V3/V4 ablations.

Modes, all ending in the same merge (:func:`merge_segments`):

- ``ours``: :func:`selfseg.method.matching.match_all`, then the three pruning criteria
  (:func:`selfseg.method.pruning.prune_matches`).
- ``v3_no_pruning``: every node pair of every non-empty optimal match is accepted.
- ``v4_registration_only``: no graph matching. Every component of every scene is registered to
  every component of every later scene; a node pair (i, k) is accepted when its precision,
  recall and feature cosine similarity are all ≥ 0.9 (greedy one-to-one, best min(P, R) first).
  Its "edge map" holds the source edges whose endpoints' partners are adjacent in the target.

**Merge rule.** Within each scene, two segments are merged when an accepted match maps a source
edge ij onto a target edge kl with both node pairs (i→k, j→l) accepted: i and j are merged in the
source scene, k and l in the target scene. Merges are the connected components of these edges
over all matches (union-find), i.e. the connected parts of the matched subgraphs that survived
pruning. A segment never merged keeps its own label. Labels are then renumbered 0..n−1 by the
smallest segment id of each group.

``matches.json`` in ``out_dir`` records, for every non-empty match: the node and edge maps, J
and T1, the registration (transform, fitness, RMSE) and per node pair precision, recall, the
decision and its reason; plus matching statistics and each scene's merged groups.
``diagnostics.json`` (:func:`diagnostics`) sums up what the step did, stage by stage.
"""
from __future__ import annotations

import concurrent.futures as cf
import hashlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
import time
from typing import Literal, Sequence

import numpy as np
from tqdm import tqdm

from selfseg.config import to_dict
from selfseg.executor import make_executor
from selfseg.fileio import dumps_json, exclusive_lock, read_json, write_json
from selfseg.method.matching import MatchConfig, PairMatch, SceneGraph, cosine_distance, match_all, match_stats
from selfseg.method.pruning import MatchDecision, NodeDecision, PruneConfig, prune_matches, register_clouds
from selfseg.method.registration import precision_recall
from selfseg.method.segment_graph import SegmentGraph


# Files written to make_pseudo_labels' out_dir.
MATCHES_JSON = "matches.json"  # every non-empty match: maps, J, T1, registration, node decisions; merged groups
# In a match cache folder (make_pseudo_labels' match_cache): match_all's result for one set of scene graphs and one
# MatchConfig (its worker count aside), so that runs differing only after matching (ours, V3) match once
MATCH_CACHE_JSON = "matches-{key_hash}.json"
# held while one run computes that entry, so a run that needs the same matching at the same time waits and reads it
MATCH_CACHE_LOCK = ".matches-{key_hash}.lock"
DIAGNOSTICS_JSON = "diagnostics.json"  # what matching and pruning did, stage by stage (:func:`diagnostics`)
# node-pair rejection reasons in the order pruning applies them (criterion 1, 2, 3)
REJECTION_ORDER = ("cost_above_T1", "no_mapped_edge", "registration_failed", "precision_recall", "isolation")


@dataclass
class PseudoLabelConfig:
    mode: Literal["ours", "v3_no_pruning", "v4_registration_only"] = "ours"
    match: MatchConfig = field(default_factory=MatchConfig)
    prune: PruneConfig = field(default_factory=PruneConfig)  # alpha, pr_thresh, registration
    cos_thresh: float = 0.9  # V4: minimum feature cosine similarity of a node pair


@dataclass
class SceneData:
    """One scene: world points (N×3), its segment graph (labels per point) and S×D segment
    features (row s = segment s)."""

    scene_id: str
    points_w: np.ndarray
    graph: SegmentGraph
    features: np.ndarray


def segment_clouds(scene: SceneData, max_points: int, seed: int) -> list[np.ndarray]:
    """Points of each segment, deterministically subsampled to at most ``max_points``."""
    labels = np.asarray(scene.graph.labels)
    n_seg = len(scene.features)
    if len(labels) != len(scene.points_w):
        raise ValueError(f"scene {scene.scene_id}: {len(scene.points_w)} points but {len(labels)} labels")
    if labels.max(initial=-1) >= n_seg:
        raise ValueError(f"scene {scene.scene_id}: label {labels.max()} but only {n_seg} feature rows")
    order = np.argsort(labels, kind="stable")
    starts = np.searchsorted(labels[order], np.arange(n_seg + 1))
    rng = np.random.default_rng(seed)
    out = []
    for s in range(n_seg):
        idx = order[starts[s]:starts[s + 1]]
        if len(idx) > max_points:
            idx = np.sort(rng.choice(idx, max_points, replace=False))
        out.append(np.asarray(scene.points_w[idx], dtype=np.float64))
    return out


def merge_segments(n_segments: Sequence[int], decisions: Sequence[MatchDecision]) -> list[np.ndarray]:
    """Object id per segment for each scene (see the module docstring's merge rule)."""
    parent = [np.arange(n) for n in n_segments]

    def find(s: int, a: int) -> int:
        p = parent[s]
        while p[a] != a:
            p[a] = p[p[a]]
            a = p[a]
        return a

    def union(s: int, a: int, b: int) -> None:
        ra, rb = find(s, a), find(s, b)
        if ra != rb:
            parent[s][max(ra, rb)] = min(ra, rb)

    for d in decisions:
        for (i, j), (k, l) in d.accepted_edges():
            union(d.src_scene, i, j)
            union(d.tgt_scene, k, l)
    out = []
    for s, n in enumerate(n_segments):
        roots = np.array([find(s, a) for a in range(n)], dtype=np.int64)
        _, obj = np.unique(roots, return_inverse=True)  # roots are group minima: ordered by smallest id
        out.append(obj.astype(np.int32))
    return out


def match_outcome(n_merged_edges: int, rejected_reasons: Sequence[str]) -> str:
    """A decision's fate as :func:`diagnostics` counts it: "merged" with an accepted edge, else the earliest
    criterion among its rejected node pairs' reasons (:data:`REJECTION_ORDER`), else "no_accepted_edge"."""
    if n_merged_edges:
        return "merged"
    return min(rejected_reasons, key=REJECTION_ORDER.index) if rejected_reasons else "no_accepted_edge"


def diagnostics(scene_ids: Sequence[str], graphs: Sequence[SceneGraph], stats: dict,
                decisions: Sequence[MatchDecision], objects: Sequence[np.ndarray]) -> dict:
    """What matching and pruning did (``diagnostics.json``).

    - ``scenes``: per scene id: segments, components, objects after merging, merged_segments (segments
      in a group of two or more) and merges (segments − objects: the union operations that joined two groups);
    - ``matching``: component pairs, pre-filtered (optimum provably empty), solved, non-empty matches
      (:func:`selfseg.method.matching.match_stats`; empty for V4);
    - ``pruning``: decisions (non-empty matches, or V4 registered component pairs); ``matches_by_outcome``:
      each decision's fate by criterion ("cost_above_T1" = criterion 1, "no_mapped_edge",
      "registration_failed" / "precision_recall" (some pair below P/R) = criterion 2, "isolation" =
      criterion 3, "merged" = at least one accepted edge, "no_accepted_edge" = pairs accepted but no edge
      with both ends accepted); ``node_pairs_by_reason``: every matched node pair's reason;
    - ``merges``: accepted cross-scene edges, within-scene merge edges {scene: [[i, j], ...]} and the
      cross-scene node pairs that carried them [[scene_a, i, scene_b, k], ...] (segment ids of each scene).
    """
    outcome: Counter = Counter()
    reasons: Counter = Counter()
    within: dict[str, set] = {sid: set() for sid in scene_ids}
    across: set = set()
    for d in decisions:
        reasons.update(p.reason for p in d.pairs)
        edges = d.accepted_edges()
        outcome[match_outcome(len(edges), [p.reason for p in d.pairs if not p.accepted])] += 1
        a, b = scene_ids[d.src_scene], scene_ids[d.tgt_scene]
        for (i, j), (k, l) in edges:
            within[a].add((min(i, j), max(i, j)))
            within[b].add((min(k, l), max(k, l)))
            across.update({(a, i, b, k), (a, j, b, l)})
    scenes = {}
    for sid, g, obj in zip(scene_ids, graphs, objects):
        sizes = np.bincount(obj, minlength=obj.max(initial=-1) + 1)
        scenes[sid] = {"segments": len(obj), "components": len(g.components), "objects": int(len(sizes)),
                       "merged_segments": int(sizes[sizes > 1].sum()), "merges": int(len(obj) - len(sizes))}
    return {
        "scenes": scenes,
        "totals": {k: sum(s[k] for s in scenes.values()) for k in ("segments", "components", "merged_segments",
                                                                    "merges")},
        "matching": {k: stats[k] for k in ("component_pairs", "prefiltered", "solved", "nonempty", "time_limit_hits",
                                           "milp_nodes_max") if k in stats},
        "pruning": {"decisions": len(decisions), "matches_by_outcome": dict(sorted(outcome.items())),
                    "node_pairs_by_reason": dict(sorted(reasons.items()))},
        "merges": {"accepted_edges": sum(len(d.accepted_edges()) for d in decisions),
                   "within": {sid: sorted(map(list, e)) for sid, e in within.items()},
                   "across": sorted(map(list, across))},
    }


def _v4_component_pair(sa: int, ca: int, sb: int, cb: int, src_nodes, tgt_nodes, clouds_a, clouds_b,
                       f_src, f_tgt, edges_a, edges_b, cfg: PseudoLabelConfig) -> MatchDecision | None:
    """V4: register component ca of scene sa onto cb of scene sb and accept node pairs.

    ``f_src``/``f_tgt`` are the features of ``src_nodes``/``tgt_nodes`` (same order). A pair of components
    with no node pair at the cosine threshold can accept nothing, so it is not registered (registration is
    seeded per call: skipping one changes no other)."""
    pc = cfg.prune
    cos = 1.0 - cosine_distance(f_src, f_tgt)
    if not (cos >= cfg.cos_thresh).any():
        return None
    record = register_clouds(np.concatenate([clouds_a[i] for i in src_nodes]),
                             np.concatenate([clouds_b[k] for k in tgt_nodes]), pc)
    if "error" in record:
        return None
    T = np.asarray(record["T_tgt_src"])
    cands = []
    for a, i in enumerate(src_nodes):
        for b, k in enumerate(tgt_nodes):
            if cos[a, b] >= cfg.cos_thresh:
                p, r = precision_recall(clouds_a[i], clouds_b[k], T, pc.dist_thresh_m)
                if p >= pc.pr_thresh and r >= pc.pr_thresh:
                    cands.append((-min(p, r), int(i), int(k), p, r, float(cos[a, b])))
    pairs, used_i, used_k = [], set(), set()
    for _, i, k, p, r, c in sorted(cands):
        if i not in used_i and k not in used_k:
            used_i.add(i)
            used_k.add(k)
            pairs.append(NodeDecision(i, k, True, "accepted", p, r, c))
    if not pairs:
        return None
    node_map = {p.src: p.tgt for p in pairs}
    tgt_edges = {tuple(e) for e in np.sort(edges_b, axis=1).tolist()}
    edge_map = [((i, j), (node_map[i], node_map[j])) for i, j in np.sort(edges_a, axis=1).tolist()
                if i in node_map and j in node_map and tuple(sorted((node_map[i], node_map[j]))) in tgt_edges]
    return MatchDecision(sa, ca, sb, cb, node_map, edge_map, pairs, status="v4_registration", registration=record)


def _v4_decisions(graphs: list[SceneGraph], clouds: list[list[np.ndarray]], cfg: PseudoLabelConfig,
                  executor: cf.Executor | None, progress: bool) -> list[MatchDecision]:
    """V4 decisions for every component pair of every scene pair (scene a < scene b)."""
    jobs = []
    for sa in range(len(graphs)):
        for sb in range(sa + 1, len(graphs)):
            for ca, src in enumerate(graphs[sa].components):
                for cb, tgt in enumerate(graphs[sb].components):
                    # only this pair's nodes and edges travel to the worker
                    ea = graphs[sa].edges[np.isin(graphs[sa].edges[:, 0], src)]
                    eb = graphs[sb].edges[np.isin(graphs[sb].edges[:, 0], tgt)]
                    jobs.append((sa, ca, sb, cb, src, tgt, {i: clouds[sa][i] for i in src},
                                 {k: clouds[sb][k] for k in tgt}, graphs[sa].features[src],
                                 graphs[sb].features[tgt], ea, eb, cfg))
    results = (_v4_component_pair(*j) for j in jobs) if executor is None else \
        (executor.map(_v4_component_pair, *zip(*jobs)) if jobs else iter(()))
    return [d for d in tqdm(results, total=len(jobs), desc="V4 registrations", disable=not progress) if d]


def make_pseudo_labels(scenes: Sequence[SceneData], cfg: PseudoLabelConfig, out_dir: str | Path,
                       executor: cf.Executor | None = None, progress: bool = True,
                       match_cache: str | Path | None = None) -> dict[str, np.ndarray]:
    """Per-point object pseudo-labels (int32, −1 where the point has no segment) per scene id.

    Writes ``out_dir/matches.json``. ``executor`` (any ``concurrent.futures.Executor``) runs the
    matching tasks and registrations; without it a local process pool
    (:func:`selfseg.executor.make_executor`) with ``cfg.match.workers`` processes is used (everything in-process when ``workers`` ≤ 1).
    ``match_cache``: a folder where the matching is kept and looked up (:func:`cached_match_all`).
    """
    own = executor is None and cfg.match.workers > 1
    ex = make_executor("local", workers=cfg.match.workers) if own else executor
    try:
        return _make_pseudo_labels(scenes, cfg, Path(out_dir), ex, progress,
                                   None if match_cache is None else Path(match_cache))
    finally:
        if own:
            ex.shutdown()


def match_key(graphs: Sequence[SceneGraph], cfg: MatchConfig) -> str:
    """What a matching's result depends on, hashed: every scene graph (id, features' and edges' bytes, components)
    and the MatchConfig but its worker count (which only spreads the same tasks)."""
    h = hashlib.sha256(dumps_json({k: v for k, v in to_dict(cfg).items() if k != "workers"}, indent=None).encode())
    for g in graphs:
        h.update(g.scene_id.encode() + b"\0")
        for a in (np.ascontiguousarray(g.features, np.float64), np.ascontiguousarray(g.edges, np.int64),
                  *(np.ascontiguousarray(c, np.int64) for c in g.components)):
            h.update(str(a.shape).encode() + a.tobytes())
    return h.hexdigest()[:16]


def cached_match_all(graphs: Sequence[SceneGraph], cfg: MatchConfig, cache: Path | None,
                     executor: cf.Executor | None, progress: bool) -> tuple[list[PairMatch], bool]:
    """(:func:`match_all`'s result, whether it came from ``cache``): read from ``cache`` (MATCH_CACHE_JSON) when a
    matching of the same graphs and config is there, else computed and written there (None: no cache). While one
    process computes an entry another that needs it waits for it (MATCH_CACHE_LOCK) rather than solving it twice. A
    matching that passes its budget raises as before and leaves nothing in the cache."""
    if cache is None:
        return match_all(graphs, cfg, executor, progress), False
    key = match_key(graphs, cfg)
    path = cache / MATCH_CACHE_JSON.format(key_hash=key)
    with exclusive_lock(cache / MATCH_CACHE_LOCK.format(key_hash=key), f"matching {key}", wait=True):
        if path.is_file():
            return [PairMatch.from_json(m) for m in read_json(path)["matches"]], True
        matches = match_all(graphs, cfg, executor, progress)
        write_json(path, {"config": to_dict(cfg), "scenes": [g.scene_id for g in graphs],
                          "matches": [m.to_json() for m in matches]})
    return matches, False


def _make_pseudo_labels(scenes: Sequence[SceneData], cfg: PseudoLabelConfig, out_dir: Path,
                        executor: cf.Executor | None, progress: bool, match_cache: Path | None
                        ) -> dict[str, np.ndarray]:
    ids = [s.scene_id for s in scenes]
    if len(set(ids)) != len(ids):
        raise ValueError("scene ids must be unique")
    graphs = []
    for s in scenes:
        feats = np.asarray(s.features, dtype=np.float64)
        if feats.ndim != 2 or len(feats) != len(s.graph.sizes):
            raise ValueError(f"scene {s.scene_id}: {feats.shape} features for {len(s.graph.sizes)} segments")
        graphs.append(SceneGraph(s.scene_id, feats, np.asarray(s.graph.edges, dtype=np.int64).reshape(-1, 2),
                                 [np.asarray(c, dtype=np.int64) for c in s.graph.components()]))
    pc = cfg.prune
    t0 = time.perf_counter()
    clouds = [segment_clouds(s, pc.max_points_per_node, pc.seed) for s in scenes]
    seconds = {"clouds_s": time.perf_counter() - t0}
    stats: dict = {}
    cached = None  # whether the matching came from the match cache (None: no matching)
    if cfg.mode == "v4_registration_only":
        t0 = time.perf_counter()
        decisions = _v4_decisions(graphs, clouds, cfg, executor, progress)
        seconds["registration_s"] = time.perf_counter() - t0
    else:
        t0 = time.perf_counter()
        matches, cached = cached_match_all(graphs, cfg.match, match_cache, executor, progress)
        seconds["matching_s"] = time.perf_counter() - t0
        stats = match_stats(matches, cfg.match)  # of the matching as computed (its CPU too, when cached)
        if cfg.mode == "ours":
            t0 = time.perf_counter()
            decisions = prune_matches(matches, lambda s, seg: clouds[s][seg], pc, executor, progress)
            seconds["pruning_s"] = time.perf_counter() - t0  # registration included
        elif cfg.mode == "v3_no_pruning":
            decisions = [MatchDecision(m.src_scene, m.src_comp, m.tgt_scene, m.tgt_comp, m.result.node_map,
                                       m.result.edge_map,
                                       [NodeDecision(i, k, True, "no_pruning") for i, k in m.result.node_map.items()],
                                       m.result.cost, None, m.result.status)
                         for m in matches if m.result.node_map]
        else:
            raise ValueError(f"unknown pseudo-label mode {cfg.mode!r}")
    objects = merge_segments([len(g.features) for g in graphs], decisions)
    labels = {}
    groups = {}
    for scene, obj in zip(scenes, objects):
        seg = np.asarray(scene.graph.labels, dtype=np.int64)
        labels[scene.scene_id] = np.where(seg >= 0, obj[np.maximum(seg, 0)], -1).astype(np.int32)
        groups[scene.scene_id] = [np.nonzero(obj == o)[0].tolist() for o in range(obj.max(initial=-1) + 1)
                                  if (obj == o).sum() > 1]
    write_json(out_dir / MATCHES_JSON, {
        "config": to_dict(cfg), "mode": cfg.mode, "scenes": ids, "match_stats": stats,
        "n_decisions": len(decisions),
        "n_merged_edges": sum(len(d.accepted_edges()) for d in decisions),
        "merged_groups": groups,
        "matches": [d.to_json(ids) for d in decisions],
    })
    write_json(out_dir / DIAGNOSTICS_JSON, {"mode": cfg.mode, **diagnostics(ids, graphs, stats, decisions, objects),
                                            "matching_from_cache": cached,
                                            "timings_s": {k: round(v, 3) for k, v in seconds.items()}})
    return labels
