"""False-match pruning (paper step 6): the three criteria and a per-node-pair decision record.

Criteria, applied in the paper's order 1 → 2 → 3:

1. **Cost.** Keep a match only if J < T1 = α·(|V1| + |E1|) (α = 0.1). J includes the constant
   (see :mod:`selfseg.method.matching`), so with α equal to both deletion costs T1 is exactly the
   empty match's cost and criterion 1 keeps the matches strictly better than matching nothing;
   a smaller α demands a better match.
2. **Registration.** The point clouds of the matched source and target nodes are registered
   (FPFH + RANSAC, then ICP; :func:`selfseg.method.registration.register`). Each matched node
   pair then gets precision (share of its aligned source points within ``dist_thresh_m`` of the
   target node's points) and recall (the reverse); a pair below ``pr_thresh`` on either is not
   merged. ``dist_thresh_m`` = ``pr_dist_voxels`` × ``reg_voxel_m`` (2 × 6 mm): a point cloud
   sampled at one voxel lies within about one voxel of another sampling of the same surface,
   and ICP's residual adds a few mm.
3. **Isolation.** If a whole source component G1 matches a subgraph S = (V', E') of a target
   component with |V1| = |V'|, then every other match into that target component whose
   matched node set strictly contains V' is dropped. Victims are taken among the matches that
   pass criterion 1; a witness must also have registered with every node pair's precision and
   recall ≥ ``witness_pr_thresh`` (default: T2), so an unverified match (e.g. a single look-alike
   segment) cannot veto a registered object. A separate witness threshold lets T2 be relaxed for
   merging (inconsistent over-segmentation) without making every registered match a witness.
   With ``isolation_cover`` set (a departure from the paper, for over-segmentation that differs
   between scenes), a witness vetoes a match only if one of the extra target nodes (V̂ minus V')
   is not part of the witnessed object: less than ``isolation_cover`` of its points lie within
   ``dist_thresh_m`` of the witness's source component under the witness's registration. The
   paper's criterion assumes the isolated object splits into the same parts in both scenes; when
   it is one segment in the source and several in the target, its other target parts are
   covered by the registered source, while another object's segments are not.
"""
from __future__ import annotations

import concurrent.futures as cf
from collections import defaultdict
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from tqdm import tqdm

from selfseg.method.matching import PairMatch
from selfseg.method.registration import RegistrationError, precision_recall, register
from selfseg.poses import invert_T


@dataclass
class PruneConfig:
    """Thresholds of the three criteria and the registration settings."""

    alpha: float = 0.1  # criterion 1: T1 = alpha·(|V1| + |E1|)
    pr_thresh: float = 0.9  # criterion 2: per node pair precision and recall
    witness_pr_thresh: float | None = None  # criterion 3: a witness's per node pair P and R (None: pr_thresh)
    isolation_cover: float | None = None  # criterion 3: extra nodes covered this much do not veto (None: paper)
    reg_voxel_m: float = 0.006  # registration voxel (segments are a few cm)
    pr_dist_voxels: float = 2.0  # precision/recall distance threshold in voxels
    max_points_per_node: int = 3000  # deterministic subsample per segment for registration and P/R
    seed: int = 0

    @property
    def dist_thresh_m(self) -> float:
        return self.pr_dist_voxels * self.reg_voxel_m


@dataclass
class NodeDecision:
    """Fate of one matched node pair (src segment → tgt segment)."""

    src: int
    tgt: int
    accepted: bool
    # "accepted", "no_pruning", "cost_above_T1", "no_mapped_edge", "registration_failed",
    # "precision_recall", "isolation"
    reason: str
    precision: float | None = None
    recall: float | None = None
    cosine: float | None = None


@dataclass
class MatchDecision:
    """A non-empty match (or, for V4, a registered component pair) and what pruning made of it.

    ``edge_map`` pairs ((i, j), (k, l)) with i → k and j → l; :meth:`accepted_edges` keeps those
    whose two node pairs were both accepted: merging follows exactly these edges.
    """

    src_scene: int
    src_comp: int
    tgt_scene: int
    tgt_comp: int
    node_map: dict[int, int]
    edge_map: list[tuple[tuple[int, int], tuple[int, int]]]
    pairs: list[NodeDecision]
    cost: float | None = None  # J (None for V4)
    T1: float | None = None
    status: str = ""
    isolation_witness: int | None = None  # index of the match that triggered criterion 3
    registration: dict | None = None

    def accepted_edges(self) -> list[tuple[tuple[int, int], tuple[int, int]]]:
        ok = {(p.src, p.tgt) for p in self.pairs if p.accepted}
        return [(s, t) for s, t in self.edge_map if (s[0], t[0]) in ok and (s[1], t[1]) in ok]

    def to_json(self, scene_ids: Sequence[str]) -> dict:
        return {
            "src_scene": scene_ids[self.src_scene], "src_comp": self.src_comp,
            "tgt_scene": scene_ids[self.tgt_scene], "tgt_comp": self.tgt_comp,
            "J": self.cost, "T1": self.T1, "status": self.status,
            "node_map": [[i, k] for i, k in sorted(self.node_map.items())],
            "edge_map": [list(map(list, e)) for e in self.edge_map],
            "merged_edges": [list(map(list, e)) for e in self.accepted_edges()],
            "isolation_witness": self.isolation_witness,
            "registration": self.registration,
            "pairs": [vars(p) for p in self.pairs],
        }


def criterion_cost(m: PairMatch, alpha: float) -> tuple[bool, float]:
    """Criterion 1: (J < T1, T1) with T1 = alpha·(|V1| + |E1|) of the source component."""
    T1 = alpha * (m.n_src_nodes + m.n_src_edges)
    return m.result.cost < T1, T1


def criterion_isolation(matches: Sequence[PairMatch], can_witness: Sequence[bool] | None = None,
                        explained: Callable[[int, set[int]], bool] | None = None) -> dict[int, int]:
    """Criterion 3 over ``matches``: {index of a dropped match: index of its witness}.

    A witness maps every node of its source component (|V1| = |V'|) into a target component
    (and has ``can_witness`` true, if given); any other match into the same target component
    whose target node set strictly contains the witness's V' is dropped, unless
    ``explained(witness, extra target nodes)`` says those nodes belong to the witnessed object.
    """
    by_target: dict[tuple[int, int], list[int]] = defaultdict(list)
    for n, m in enumerate(matches):
        by_target[(m.tgt_scene, m.tgt_comp)].append(n)
    dropped: dict[int, int] = {}
    for members in by_target.values():
        for w in members:
            mw = matches[w]
            if len(mw.result.node_map) != mw.n_src_nodes or (can_witness is not None and not can_witness[w]):
                continue
            S = set(mw.result.node_map.values())
            for v in members:
                V = set(matches[v].result.node_map.values())
                if v not in dropped and v != w and S < V and not (explained and explained(w, V - S)):
                    dropped[v] = w
    return dropped


def register_clouds(src: np.ndarray, tgt: np.ndarray, cfg: PruneConfig) -> dict:
    """Registration record of two clouds: T_tgt_src (4×4 list), fitness, rmse, or {"error": ...}."""
    try:
        reg = register(src, tgt, cfg.reg_voxel_m, seed=cfg.seed)
    except RegistrationError as e:
        return {"error": str(e)}
    return {"T_tgt_src": reg.T_tgt_src.tolist(), "fitness": reg.fitness, "rmse": reg.rmse,
            "voxel_m": cfg.reg_voxel_m, "dist_thresh_m": cfg.dist_thresh_m}


def criterion_registration(src_clouds: dict[int, np.ndarray], tgt_clouds: dict[int, np.ndarray],
                           node_map: dict[int, int], T_tgt_src: np.ndarray,
                           cfg: PruneConfig) -> dict[int, tuple[float, float, bool]]:
    """Criterion 2 given the registration of the matched subgraphs: per source node
    (precision, recall, accepted) of its pair, accepted when both are ≥ ``cfg.pr_thresh``."""
    out = {}
    for i, k in node_map.items():
        p, r = precision_recall(src_clouds[i], tgt_clouds[k], T_tgt_src, cfg.dist_thresh_m)
        out[i] = (p, r, p >= cfg.pr_thresh and r >= cfg.pr_thresh)
    return out


def prune_matches(matches: Sequence[PairMatch], clouds: Callable[[int, int], np.ndarray], cfg: PruneConfig,
                  executor: cf.Executor | None = None, progress: bool = True) -> list[MatchDecision]:
    """Apply criteria 1, 2 and 3 to the non-empty ``matches``; one decision per match.

    ``clouds(scene, segment)`` returns a segment's points (already subsampled). Every node pair
    of every match gets a decision and a reason. Two shortcuts leave the merges unchanged:

    - a match with no mapped edge can merge nothing (merging follows mapped edges), so unless
      it maps a whole source component (a potential isolation witness) it is not registered
      and its pairs get reason "no_mapped_edge";
    - matches A→B and B→A between the same two node sets share one registration (the reverse
      one uses the inverse transform; precision and recall are symmetric under it).

    Registrations run on ``executor`` when given, else in this process.
    """
    matches = [m for m in matches if m.result.node_map]
    decisions = []
    for m in matches:
        ok, T1 = criterion_cost(m, cfg.alpha)
        d = MatchDecision(m.src_scene, m.src_comp, m.tgt_scene, m.tgt_comp, dict(m.result.node_map),
                          list(m.result.edge_map), [], m.result.cost, T1, m.result.status)
        if not ok:
            d.pairs = [NodeDecision(i, k, False, "cost_above_T1") for i, k in m.result.node_map.items()]
        elif not d.edge_map and len(d.node_map) != m.n_src_nodes:
            d.pairs = [NodeDecision(i, k, False, "no_mapped_edge") for i, k in m.result.node_map.items()]
        decisions.append(d)
    to_register = [n for n, d in enumerate(decisions) if not d.pairs]

    def key(d: MatchDecision):
        return (d.src_scene, tuple(sorted(d.node_map))), (d.tgt_scene, tuple(sorted(d.node_map.values())))

    jobs: dict = {}
    for n in to_register:
        (s, src), (t, tgt) = key(decisions[n])
        if ((t, tgt), (s, src)) not in jobs:
            jobs.setdefault(((s, src), (t, tgt)), (np.concatenate([clouds(s, i) for i in src]),
                                                   np.concatenate([clouds(t, k) for k in tgt])))
    args = list(jobs.values())
    if executor is None:
        records = (register_clouds(a, b, cfg) for a, b in args)
    else:
        records = executor.map(register_clouds, [a for a, _ in args], [b for _, b in args],
                               [cfg] * len(args)) if args else iter(())
    done = dict(zip(jobs, tqdm(records, total=len(args), desc="registering matches", disable=not progress)))
    for n in to_register:
        d = decisions[n]
        src_key, tgt_key = key(d)
        record = done.get((src_key, tgt_key))
        if record is None:  # registered in the other direction
            record = dict(done[(tgt_key, src_key)], reversed=True)
            if "T_tgt_src" in record:
                record["T_tgt_src"] = invert_T(np.asarray(record["T_tgt_src"])).tolist()
        d.registration = record
        if "error" in record:
            d.pairs = [NodeDecision(i, k, False, "registration_failed") for i, k in d.node_map.items()]
            continue
        scores = criterion_registration({i: clouds(d.src_scene, i) for i in d.node_map},
                                        {k: clouds(d.tgt_scene, k) for k in d.node_map.values()},
                                        d.node_map, np.asarray(record["T_tgt_src"]), cfg)
        d.pairs = [NodeDecision(i, k, scores[i][2], "accepted" if scores[i][2] else "precision_recall",
                                scores[i][0], scores[i][1]) for i, k in d.node_map.items()]
    wt = cfg.pr_thresh if cfg.witness_pr_thresh is None else cfg.witness_pr_thresh
    verified = [all(p.reason == "accepted" and p.precision >= wt and p.recall >= wt for p in decisions[n].pairs)
                for n in to_register]

    def explained(w: int, extra: set[int]) -> bool:
        """Every extra target node covered ≥ isolation_cover by witness w's registered source component."""
        d = decisions[to_register[w]]
        src = np.concatenate([clouds(d.src_scene, i) for i in d.node_map])
        T = np.asarray(d.registration["T_tgt_src"])
        return all(precision_recall(src, clouds(d.tgt_scene, k), T, cfg.dist_thresh_m)[1] >= cfg.isolation_cover
                   for k in extra)

    for v, w in criterion_isolation([matches[n] for n in to_register], verified,
                                    None if cfg.isolation_cover is None else explained).items():
        d = decisions[to_register[v]]
        d.isolation_witness = to_register[w]
        for p in d.pairs:
            if p.accepted:
                p.accepted, p.reason = False, "isolation"
    return decisions
