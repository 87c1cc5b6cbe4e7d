"""Error-tolerant minimum-cost subgraph matching of segment graphs (paper step 5).

Formulation (Lu et al. 2023, after Lerouge et al.), for a source graph G1 = (V1, E1) and a
target graph G2 = (V2, E2), both undirected::

    J = min  Σ_ik x_ik (c(i→k) − c_del_node) + Σ_{ij,kl} y_ij,kl (0 − c_del_edge)
             + c_del_node·|V1| + c_del_edge·|E1|
    s.t.     Σ_k x_ik ≤ 1  ∀i ∈ V1,      Σ_i x_ik ≤ 1  ∀k ∈ V2,
             Σ_{l: kl ∈ E2} y_ij,kl ≤ x_ik + x_jk   ∀ij ∈ E1, ∀k ∈ V2,
             x, y binary,

with c(i→k) the cosine distance 1 − cos(f_i, f_k) and edge substitution cost 0.

**The cost J includes the constant**, so it is the full edit cost of the match: the empty match
(every node and edge of G1 deleted) has J = c_del_node·|V1| + c_del_edge·|E1|, which with both
deletion costs at 0.1 equals pruning's T1 = 0.1·(|V1| + |E1|).

**Edge variables.** Each undirected edge is stored once (i < j). There is one variable
y_ij,kl per source edge ij ∈ E1 and *undirected* target edge kl ∈ E2; it stands for ij being
mapped onto kl in either orientation. The constraint above is written for every endpoint
k ∈ V2, so a y_ij,kl appears in two rows: at k and at l. With integral x these rows force
{k, l} ⊆ {f(i), f(j)}; since each source node has one image and k ≠ l, that means
{k, l} = {f(i), f(j)}, so y_ij,kl = 1 exactly when ij is mapped onto kl. We create y_ij,kl only
when one of the two orientations is possible with the node variables that exist
(x_ik and x_jl, or x_il and x_jk); every other y is 0 in any integral feasible solution. The
returned edge map orients each pair as ((i, j), (f(i), f(j))).

**Speed, exactly.** Before solving, :func:`prefilter_lower_bound` proves many instances'
optimum to be the empty match, and :func:`reduce_pairs` removes node pairs that no optimal
solution needs (both with proofs in their docstrings). The rest are solved as stacked LP
relaxations and, for non-integral blocks, a stacked MILP (:func:`match_batch`).

**Indices.** :func:`match_graphs` and :func:`match_costs` return node and edge maps in the
local row indices of their inputs; :func:`match_all` returns them in the scenes' global segment
ids.
"""
from __future__ import annotations

import concurrent.futures as cf
import math
import multiprocessing
import resource
import signal
import time
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import Literal, Sequence

import numpy as np
import scipy.sparse as sp
from scipy.optimize import Bounds, LinearConstraint, linprog, milp
from tqdm import tqdm

from selfseg.executor import make_executor
from selfseg.method_api import BudgetExceededError

# "time_limit": the MILP stopped at a limit, its time limit or its node limit, so the match is not proven optimal
Status = Literal["prefiltered_empty", "lp_integral", "milp_optimal", "time_limit"]


@dataclass
class MatchConfig:
    """Matching costs and solver settings."""

    c_del_node: float = 0.1  # cost of deleting a source node (paper: 0.1)
    c_del_edge: float = 0.1  # cost of deleting a source edge (paper: 0.1)
    time_limit_s: float = 20.0  # per MILP solve, wall-clock; hits are reported as status "time_limit"
    # per MILP solve, HiGHS branch-and-bound nodes (None: no limit); hits are reported as status "time_limit" too.
    # Unlike the time limit it does not depend on the machine or its load, so where solves reach a limit this one
    # should be the one they reach, with time_limit_s far above it as a safety net.
    node_limit: int | None = None
    # branch-and-bound nodes the stacked MILP of several instances may take before its blocks are solved one by one
    # (each with node_limit): a stack holding one hard block would otherwise spend node_limit nodes on LPs of every
    # block. 10× the most a stack took on calibrated dev seed 7 (5 nodes), so calibrated's stacks solve stacked
    stack_node_limit: int = 50
    lp_first: bool = True  # solve the LP relaxation first and accept it when integral
    prefilter: bool = True  # exact pre-filter bound and variable reduction (see prefilter())
    mip_rel_gap: float = 1e-7  # HiGHS relative gap at which a MILP solution counts as optimal
    int_tol: float = 1e-6  # an LP value within this of 0 or 1 counts as integral
    workers: int = 2  # processes for match_all when no executor is given (≤ 1: in-process)
    # CPU seconds match_all may spend per pair of scenes it matches (None: no budget), summed over all its tasks; past
    # it, MatchBudgetError. Per pair, so a fold's matching and Table II's (every scene) get the same rule; counted
    # in CPU, not wall time, so the verdict does not depend on the machine's load (see match_all)
    cpu_budget_per_pair_s: float | None = None
    pairs_per_task: int = 8  # scene pairs solved as one stacked batch per executor task


@dataclass
class MatchResult:
    """Optimal (or best found) match of a source graph into a target graph.

    ``cost`` is J including the constant (empty match: c_del_node·|V1| + c_del_edge·|E1|);
    ``status`` says how optimality was established, and "time_limit" means it was not.
    """

    node_map: dict[int, int]
    edge_map: list[tuple[tuple[int, int], tuple[int, int]]]
    cost: float
    status: Status
    solve_s: float
    n_vars: int = 0  # x and y variables after the exact reduction (0 when prefiltered)
    milp_nodes: int = 0  # branch-and-bound nodes of the MILP solve it took part in (0: none)
    # "time_limit" only: the MILP's lower bound on J at the limit (HiGHS's dual bound plus the constant); None
    # where optimality is proven or no bound was reported
    cost_bound: float | None = None

    @property
    def proven_optimal(self) -> bool:
        return self.status != "time_limit"

    def limit_gap(self, n_src_nodes: int, n_src_edges: int, cfg: MatchConfig) -> float | None:
        """Of the most the match could gain over the empty match (J_empty − bound), the share this match may
        miss: (J − bound) / (J_empty − bound), at least 0; 0 when proven optimal, None at a limit without a
        bound."""
        if self.proven_optimal:
            return 0.0
        if self.cost_bound is None:
            return None
        room = empty_match_cost(n_src_nodes, n_src_edges, cfg) - self.cost_bound
        return max(0.0, (self.cost - self.cost_bound) / room) if room > 0 else 0.0  # ≥ 0 but for rounding


@dataclass
class SceneGraph:
    """What matching needs of one scene: features, undirected edges and components.

    ``features``: S×D (rows are segment ids); ``edges``: E×2 int (i < j); ``components``:
    arrays of segment ids, one per weakly connected component.
    """

    scene_id: str
    features: np.ndarray
    edges: np.ndarray
    components: list[np.ndarray]


@dataclass
class PairMatch:
    """Result of matching component ``src_comp`` of scene ``src_scene`` into ``tgt_comp``.

    Scenes are indices into the list given to :func:`match_all`; the match's node and edge maps
    use global segment ids of the two scenes. ``n_src_nodes``/``n_src_edges`` are |V1|, |E1|.
    """

    src_scene: int
    src_comp: int
    tgt_scene: int
    tgt_comp: int
    n_src_nodes: int
    n_src_edges: int
    result: MatchResult = field(repr=False)
    cpu_s: float = 0.0  # its equal share of the CPU seconds of the task (scene pairs) that solved it

    def to_json(self) -> dict:
        """A JSON-able dict that :meth:`from_json` turns back into an equal PairMatch (floats exactly)."""
        r = self.result
        return {"src_scene": self.src_scene, "src_comp": self.src_comp, "tgt_scene": self.tgt_scene,
                "tgt_comp": self.tgt_comp, "n_src_nodes": self.n_src_nodes, "n_src_edges": self.n_src_edges,
                "cpu_s": float(self.cpu_s), "node_map": [[int(i), int(k)] for i, k in r.node_map.items()],
                "edge_map": [[list(map(int, e1)), list(map(int, e2))] for e1, e2 in r.edge_map],
                "cost": float(r.cost), "status": r.status, "solve_s": float(r.solve_s), "n_vars": int(r.n_vars),
                "milp_nodes": int(r.milp_nodes), "cost_bound": None if r.cost_bound is None else float(r.cost_bound)}

    @classmethod
    def from_json(cls, d: dict) -> PairMatch:
        result = MatchResult({i: k for i, k in d["node_map"]}, [(tuple(e1), tuple(e2)) for e1, e2 in d["edge_map"]],
                             d["cost"], d["status"], d["solve_s"], d["n_vars"], d["milp_nodes"], d["cost_bound"])
        return cls(d["src_scene"], d["src_comp"], d["tgt_scene"], d["tgt_comp"], d["n_src_nodes"], d["n_src_edges"],
                   result, d["cpu_s"])


class MatchBudgetError(BudgetExceededError):
    """Matching spent more CPU seconds than ``MatchConfig.cpu_budget_per_pair_s`` × its scene pairs."""


def cosine_distance(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """n1×n2 matrix of 1 − cos between rows of ``f1`` and ``f2`` (rows are normalised here).

    A zero row is a segment that no frame of φ1's feature pass saw (``segment_features``' ``seen`` False): it has
    no feature, so it is at the largest distance, 2, from every row, and matching never maps it."""
    f1 = np.asarray(f1, dtype=np.float64)
    f2 = np.asarray(f2, dtype=np.float64)
    if f1.ndim != 2 or f2.ndim != 2 or f1.shape[1] != f2.shape[1]:
        raise ValueError(f"features must be n×D arrays of equal D, got {f1.shape} and {f2.shape}")
    n1 = np.linalg.norm(f1, axis=1, keepdims=True)
    n2 = np.linalg.norm(f2, axis=1, keepdims=True)
    d = 1.0 - (f1 / np.where(n1 == 0, 1.0, n1)) @ (f2 / np.where(n2 == 0, 1.0, n2)).T
    d[(n1 == 0)[:, 0], :] = 2.0
    d[:, (n2 == 0)[:, 0]] = 2.0
    return d


def _check_edges(edges: np.ndarray, n: int, name: str) -> np.ndarray:
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    if len(e) and (e.min() < 0 or e.max() >= n):
        raise ValueError(f"{name}: node index out of range [0, {n})")
    if (e[:, 0] == e[:, 1]).any():
        raise ValueError(f"{name}: self-loop")
    e = np.sort(e, axis=1)
    if len(np.unique(e[:, 0] * n + e[:, 1])) != len(e):
        raise ValueError(f"{name}: duplicate undirected edge")
    return e


def empty_match_cost(n_nodes: int, n_edges: int, cfg: MatchConfig) -> float:
    """J of the empty match: every source node and edge deleted."""
    return cfg.c_del_node * n_nodes + cfg.c_del_edge * n_edges


def _adjacency(edges: np.ndarray, n: int) -> np.ndarray:
    A = np.zeros((n, n))
    A[edges[:, 0], edges[:, 1]] = A[edges[:, 1], edges[:, 0]] = 1.0
    return A


def prefilter_lower_bound(gain: np.ndarray, m_bound: np.ndarray, cfg: MatchConfig,
                          keep: np.ndarray | None = None) -> float:
    """Lower bound L on J* − J_empty; when L ≥ 0 the empty match is optimal.

    ``gain[i, k]`` = c(i→k) − c_del_node; ``m_bound[i, k]`` bounds the number of source edges
    at i that can be mapped when i → k; ``keep`` (optional) restricts the pairs considered. The
    basic bound uses all pairs and m_bound = min(deg1(i), deg2(k)) ("each node's best
    substitution gain plus half of its best possible incident-edge gains"):

        L = Σ_i min(0, min_k [gain_ik − (c_del_edge/2)·m_bound_ik]).

    Proof. For a feasible integral (x, y) with node map f on the mapped set M ⊆ V1,
    J − J_empty = Σ_{i∈M} gain_{i f(i)} − c_del_edge·|Y|, with Y the set of mapped source edges.
    Both endpoints of a mapped edge are in M, so splitting each edge's −c_del_edge evenly over
    its two endpoints gives J − J_empty = Σ_{i∈M} [gain_{i f(i)} − (c_del_edge/2)·m_i], where
    m_i is the number of mapped edges at i. Distinct mapped edges ij, ij' at i are mapped onto
    the target edges (f(i), f(j)) ≠ (f(i), f(j')) (f is injective), so
    m_i ≤ min(deg1(i), deg2(f(i))) = m_bound_{i f(i)}. Hence each bracket is at least
    min_k [gain_ik − (c_del_edge/2)·m_bound_ik], and so at least that value's negative part;
    nodes outside M contribute 0, which is also at least their negative part. Summing,
    J − J_empty ≥ L for every feasible solution, in particular an optimal one. If L ≥ 0, no
    match beats the empty match (J − J_empty = 0), which is therefore optimal. ∎

    The same proof holds for the tighter ``m_bound`` and ``keep`` of :func:`reduce_pairs`,
    applied to the optimal solution that uses only the pairs it keeps.
    """
    if gain.size == 0:
        return 0.0
    bound = gain - 0.5 * cfg.c_del_edge * m_bound
    if keep is not None:
        bound = np.where(keep, bound, np.inf)
    return float(np.minimum(bound.min(axis=1), 0.0).sum())


def reduce_pairs(gain: np.ndarray, A1: np.ndarray, A2: np.ndarray, cfg: MatchConfig):
    """Exact variable reduction: (keep n1×n2 bool, m_bound n1×n2) such that an optimal
    solution exists that maps only kept pairs, with at most m_bound_ik mapped edges at i
    whenever i → k.

    Start from keep = all pairs and m_bound = min(deg1(i), deg2(k)); repeat until stable:
    drop (i, k) when gain_ik ≥ c_del_edge·m_bound_ik, then recompute
    m_bound_ik = min(#{j ∈ N1(i): some kept (j, l) with l ∈ N2(k)},
                     #{l ∈ N2(k): some kept (j, l) with j ∈ N1(i)}).

    Proof (induction over rounds). Assume an optimal solution uses only kept pairs (true at
    the start). In it, the mapped edges at a mapped i → k go to distinct neighbours j ∈ N1(i)
    with distinct images l ∈ N2(k) (f is injective), each (j, l) a kept pair, so their number
    m ≤ m_bound_ik. Unmapping i (x_ik and the y of the edges at i set to 0) keeps feasibility
    and changes the objective by −gain_ik + c_del_edge·m ≤ 0 when gain_ik ≥ c_del_edge·m_bound_ik,
    so the solution stays optimal. The bounds were computed from the round's kept set, which
    contains the solution's pairs before and after each such removal, so all dropped pairs can
    be unmapped together. The new m_bound, computed from the new kept set, again bounds
    every optimal solution restricted to it. ∎
    """
    m_bound = np.minimum(A1.sum(1)[:, None], A2.sum(0)[None, :])
    keep = np.ones(gain.shape, dtype=bool)
    while True:
        new = keep & (gain < cfg.c_del_edge * m_bound)
        K = new.astype(np.float64)
        m_bound = np.minimum(A1 @ ((K @ A2) > 0), ((A1 @ K) > 0) @ A2)
        if (new == keep).all():
            return keep, m_bound
        keep = new


def prefilter(C: np.ndarray, e1: np.ndarray, e2: np.ndarray, cfg: MatchConfig) -> tuple[bool, np.ndarray]:
    """(empty, keep): whether the empty match is proven optimal, and the node pairs to model.

    ``e1``, ``e2`` are m×2 edge arrays. Applies :func:`prefilter_lower_bound` with the degree
    bound, then :func:`reduce_pairs` and the bound again with its tighter edge counts. With
    ``cfg.prefilter`` False every pair is kept and only an instance with no node on one side
    counts as empty.
    """
    n1, n2 = C.shape
    keep = np.ones((n1, n2), dtype=bool)
    if n1 == 0 or n2 == 0:
        return True, keep
    if not cfg.prefilter:
        return False, keep
    gain = C - cfg.c_del_node
    A1, A2 = _adjacency(e1, n1), _adjacency(e2, n2)
    if prefilter_lower_bound(gain, np.minimum(A1.sum(1)[:, None], A2.sum(0)[None, :]), cfg) >= 0:
        return True, keep
    keep, m_bound = reduce_pairs(gain, A1, A2, cfg)
    return prefilter_lower_bound(gain, m_bound, cfg, keep) >= 0, keep


@dataclass
class _Problem:
    """One matching instance after the pre-filter: sparse BLP and what decoding needs."""

    C: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    c: np.ndarray  # objective over z = (x, y)
    A: tuple[np.ndarray, np.ndarray, np.ndarray]  # constraint triplets (rows, cols, values)
    b: np.ndarray
    xs: tuple[np.ndarray, np.ndarray]  # (i, k) of each x variable
    ys: tuple[np.ndarray, np.ndarray]  # (source edge, target edge) of each y variable
    prep_s: float = 0.0


def _build(C: np.ndarray, e1: np.ndarray, e2: np.ndarray, keep: np.ndarray, cfg: MatchConfig):
    """BLP over the kept node pairs: (c, A triplets, b, x pairs, y pairs), A z ≤ b, 0 ≤ z ≤ 1."""
    n1, n2 = C.shape
    gain = C - cfg.c_del_node
    xi, xk = np.nonzero(keep)
    nx = len(xi)
    xid = np.full((n1, n2), -1, dtype=np.int64)
    xid[xi, xk] = np.arange(nx)
    # y_e,t exists when ij → kl is possible in one orientation with existing x variables
    if len(e1) and len(e2):
        i, j = e1[:, 0][:, None], e1[:, 1][:, None]
        k, l = e2[:, 0][None, :], e2[:, 1][None, :]
        ye, yt = np.nonzero((keep[i, k] & keep[j, l]) | (keep[i, l] & keep[j, k]))
    else:
        ye = yt = np.zeros(0, dtype=np.int64)
    ny = len(ye)
    c = np.concatenate([gain[xi, xk], np.full(ny, -cfg.c_del_edge)])
    # Σ_k x_ik ≤ 1 (rows 0..n1-1) and Σ_i x_ik ≤ 1 (rows n1..n1+n2-1)
    rows = [xi, n1 + xk]
    cols = [np.arange(nx), np.arange(nx)]
    vals = [np.ones(nx), np.ones(nx)]
    # one row per (source edge e = ij, target node k) touched by some y: Σ_l y_e,kl − x_ik − x_jk ≤ 0
    ends = np.concatenate([e2[yt, 0], e2[yt, 1]])
    keys, row_of = np.unique(np.concatenate([ye, ye]) * n2 + ends, return_inverse=True)
    rows.append(n1 + n2 + row_of.ravel())
    cols.append(nx + np.concatenate([np.arange(ny), np.arange(ny)]))
    vals.append(np.ones(2 * ny))
    ke, kk = keys // n2, keys % n2
    for end in (0, 1):
        v = xid[e1[ke, end], kk] if len(keys) else np.zeros(0, dtype=np.int64)
        ok = v >= 0
        rows.append(n1 + n2 + np.nonzero(ok)[0])
        cols.append(v[ok])
        vals.append(-np.ones(int(ok.sum())))
    b = np.concatenate([np.ones(n1 + n2), np.zeros(len(keys))])
    return c, (np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)), b, (xi, xk), (ye, yt)


def _decode(z: np.ndarray, p: _Problem, cfg: MatchConfig):
    """Node map, oriented edge map and J of an integral solution ``z``."""
    xi, xk = p.xs
    nx = len(xi)
    on_x = z[:nx] > 0.5
    on_y = z[nx:] > 0.5
    node_map = {int(i): int(k) for i, k in zip(xi[on_x], xk[on_x])}
    edge_map = []
    for e, t in zip(p.ys[0][on_y], p.ys[1][on_y]):
        i, j = (int(v) for v in p.e1[e])
        k, l = (int(v) for v in p.e2[t])
        edge_map.append(((i, j), (k, l) if node_map.get(i) == k else (l, k)))
    cost = (empty_match_cost(len(p.C), len(p.e1), cfg)
            + sum(p.C[i, k] - cfg.c_del_node for i, k in node_map.items()) - cfg.c_del_edge * len(edge_map))
    return node_map, sorted(edge_map), float(cost)


def _prepare(C: np.ndarray, edges1: np.ndarray, edges2: np.ndarray, cfg: MatchConfig) -> MatchResult | _Problem:
    """Check one instance; its empty match when the pre-filter proves it optimal, else its reduced BLP.

    ``solve_s`` of the empty match and ``prep_s`` of the BLP are this step's wall time (s).
    """
    start = time.perf_counter()
    C = np.asarray(C, dtype=np.float64)
    if C.ndim != 2:
        raise ValueError(f"cost matrix must be 2-D, got shape {C.shape}")
    n1, n2 = C.shape
    e1 = _check_edges(edges1, n1, "edges1")
    e2 = _check_edges(edges2, n2, "edges2")
    empty, keep = prefilter(C, e1, e2, cfg)
    if empty:
        return MatchResult({}, [], empty_match_cost(n1, len(e1), cfg), "prefiltered_empty",
                           time.perf_counter() - start)
    p = _Problem(C, e1, e2, *_build(C, e1, e2, keep, cfg))
    p.prep_s = time.perf_counter() - start
    return p


def _node_map_array(z: np.ndarray, p: _Problem) -> np.ndarray:
    """The node map of an integral solution ``z`` of ``p`` as an n1 array of target nodes (−1: unmapped)."""
    xi, xk = p.xs
    on = z[:len(xi)] > 0.5
    f = np.full(len(p.C), -1, dtype=np.int64)
    f[xi[on]] = xk[on]
    return f


def _encode(f: np.ndarray, p: _Problem) -> np.ndarray:
    """The integral solution z of ``p`` for the node map ``f`` (n1 targets, −1: unmapped; kept pairs only): x of
    its pairs, and y of every source edge that ``f`` maps onto a target edge (each such y exists, see _build)."""
    xi, xk = p.xs
    ye, yt = p.ys
    fi, fj = f[p.e1[ye, 0]], f[p.e1[ye, 1]]
    k, l = p.e2[yt, 0], p.e2[yt, 1]
    return np.concatenate([f[xi] == xk, ((fi == k) & (fj == l)) | ((fi == l) & (fj == k))]).astype(np.float64)


def improve_match(z: np.ndarray, p: _Problem, cfg: MatchConfig, max_moves: int = 100_000) -> np.ndarray:
    """Steepest-descent local search from the integral solution ``z`` of ``p``: an integral solution whose J is
    at most ``z``'s, at which no single move lowers J.

    Moves, over the pairs the reduction kept: map an unmapped source node i to a free target k; move a mapped i
    to a free k; unmap i; give i the target k of another source node j, j taking i's target (or becoming
    unmapped when i had none). With the gain of a map f, J_empty − J = Σ_{i mapped} (c_del_node − C[i, f(i)])
    + c_del_edge·#{ij ∈ E1 mapped onto an edge of E2}, and L[i, k] = c_del_node − C[i, k] + c_del_edge·#{j ∈
    N1(i) mapped into N2(k)} (i's own terms with i at k, the others fixed), a move's change of the gain is
    L[i, k] − L[i, f(i)] for a free k (0 for "unmapped"), and for k = f(j) held by j
    L[i, k] − L[i, f(i)] + L[j, f(i)] − L[j, k] + 2·c_del_edge·[ij ∈ E1 and f(i)k ∈ E2]: the edge ij is
    counted in both L[i, f(i)] and L[j, k] before the exchange and in neither L[i, k] nor L[j, f(i)] after it,
    while it is mapped after the exchange exactly when it was before. The best move is made while it gains more
    than 1e-12.
    """
    n1, n2 = p.C.shape
    keep = np.zeros((n1, n2), dtype=bool)
    keep[p.xs] = True
    A1, A2 = _adjacency(p.e1, n1), _adjacency(p.e2, n2)
    A2x = np.vstack([A2, np.zeros((1, n2))])  # row n2: "unmapped", adjacent to nothing
    P = np.where(keep, cfg.c_del_node - p.C, -np.inf)
    f = _node_map_array(z, p)
    rows = np.arange(n1)
    for _ in range(max_moves):
        mapped = f >= 0
        F = np.zeros((n1, n2))
        F[rows[mapped], f[mapped]] = 1.0
        L = np.zeros((n1, n2 + 1))  # column n2: unmapped
        L[:, :n2] = P + cfg.c_del_edge * (A1 @ F @ A2)
        fi = np.where(mapped, f, n2)
        cur = L[rows, fi]
        holder = np.full(n2, -1, dtype=np.int64)
        holder[f[mapped]] = rows[mapped]
        j = np.maximum(holder, 0)[None, :]
        swap = L[j, fi[:, None]] - cur[j] + 2 * cfg.c_del_edge * A1[rows[:, None], j] * A2x[fi][:, :n2]
        delta = L[:, :n2] - cur[:, None] + np.where(holder[None, :] >= 0, swap, 0.0)
        delta[holder[None, :] == rows[:, None]] = -np.inf  # k is i's own target
        unmap = np.where(mapped, -cur, -np.inf)
        i, k = np.unravel_index(int(np.argmax(delta)), delta.shape)
        if max(delta[i, k], unmap.max()) <= 1e-12:
            break
        if unmap.max() > delta[i, k]:
            f[int(np.argmax(unmap))] = -1
        else:
            if holder[k] >= 0:
                f[holder[k]] = f[i]
            f[i] = k
    return _encode(f, p)


def _stack(probs: Sequence[_Problem]):
    """Block-diagonal (c, A, b) of ``probs``, with the variable and row offsets of the blocks."""
    off = np.cumsum([0] + [len(p.c) for p in probs])
    row_off = np.cumsum([0] + [len(p.b) for p in probs])
    A = sp.csr_matrix((np.concatenate([p.A[2] for p in probs]),
                       (np.concatenate([p.A[0] + row_off[n] for n, p in enumerate(probs)]),
                        np.concatenate([p.A[1] + off[n] for n, p in enumerate(probs)]))),
                      shape=(row_off[-1], off[-1]))
    c = np.concatenate([p.c for p in probs])
    b = np.concatenate([p.b for p in probs])
    return c, A, b, off, row_off


def _result(z: np.ndarray, p: _Problem, status: Status, share: float, cfg: MatchConfig,
            milp_nodes: int = 0, dual_bound: float | None = None) -> MatchResult:
    """MatchResult of the integral solution ``z`` of ``p``; ``share`` is its part of the stacked solves (s);
    ``dual_bound``: the MILP's lower bound on c·z when it stopped at a limit (``p`` solved alone)."""
    node_map, edge_map, cost = _decode(z, p, cfg)
    bound = None if dual_bound is None else empty_match_cost(len(p.C), len(p.e1), cfg) + dual_bound
    return MatchResult(node_map, edge_map, cost, status, p.prep_s + share, len(p.c), milp_nodes, bound)


def _solve_lp(probs: Sequence[_Problem], cfg: MatchConfig) -> tuple[list[np.ndarray | None], float]:
    """Stacked LP relaxation: per block its rounded solution if integral and feasible (else None),
    and the LP's wall time per block (s)."""
    start = time.perf_counter()
    c, A, b, off, row_off = _stack(probs)
    lp = linprog(c, A_ub=A, b_ub=b, bounds=(0, 1), method="highs")
    if lp.status != 0:
        raise RuntimeError(f"LP relaxation failed: status {lp.status} ({lp.message})")
    share = (time.perf_counter() - start) / len(probs)
    z = np.round(lp.x)
    bad_var = np.abs(lp.x - z) > cfg.int_tol
    bad_row = A @ z > b + 1e-9
    blocks: list[np.ndarray | None] = []
    for n in range(len(probs)):
        ok = not bad_var[off[n]:off[n + 1]].any() and not bad_row[row_off[n]:row_off[n + 1]].any()
        blocks.append(z[off[n]:off[n + 1]] if ok else None)
    return blocks, share


def _solve_milp(probs: Sequence[_Problem], cfg: MatchConfig, lp_share: float) -> list[MatchResult]:
    """Stacked MILP over ``probs``; one that stops at a limit (``cfg.time_limit_s``, ``cfg.node_limit``, and for
    more than one block ``cfg.stack_node_limit``) is re-solved block by block.

    ``lp_share`` (s) is each block's share of the LP before it.
    """
    start = time.perf_counter()
    c, A, b, off, _ = _stack(probs)
    options = {"time_limit": cfg.time_limit_s, "mip_rel_gap": cfg.mip_rel_gap}
    limit = cfg.node_limit
    if len(probs) > 1:
        limit = cfg.stack_node_limit if limit is None else min(limit, cfg.stack_node_limit)
    if limit is not None:
        options["node_limit"] = limit
    res = milp(c, integrality=np.ones(len(c)), bounds=Bounds(0, 1),
               constraints=LinearConstraint(A, -np.inf, b), options=options)
    nodes = int(getattr(res, "mip_node_count", 0) or 0)
    # scipy reports HiGHS's node limit as status 4 ("Solution limit reached", HiGHS status 16)
    at_node_limit = res.status == 4 and limit is not None and nodes >= limit
    if (res.status == 1 or at_node_limit) and len(probs) > 1:
        # the stacked MILP stopped at a limit: isolate the hard blocks
        return [r for p in probs for r in _solve_milp([p], cfg, lp_share)]
    if res.status == 0:
        status: Status = "milp_optimal"
    elif res.status == 1 or at_node_limit:  # the solution (if any) is not proven optimal
        status = "time_limit"
    else:
        raise RuntimeError(f"MILP failed: status {res.status} ({res.message})")
    x = np.round(res.x) if res.x is not None else np.zeros(len(c))
    share = lp_share + (time.perf_counter() - start) / len(probs)
    # at a limit the blocks were re-solved one by one above, so the dual bound is this block's
    dual = getattr(res, "mip_dual_bound", None) if status == "time_limit" else None
    dual = None if dual is None or not np.isfinite(dual) else float(dual)
    blocks = [x[off[n]:off[n + 1]] for n in range(len(probs))]
    if status == "time_limit":  # the incumbent (the empty match if none), improved by local search
        blocks = [improve_match(z, p, cfg) for z, p in zip(blocks, probs)]
    return [_result(z, p, status, share, cfg, nodes, dual) for z, p in zip(blocks, probs)]


def match_batch(problems: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
                cfg: MatchConfig) -> list[MatchResult]:
    """Solve independent matching instances (C n1×n2 node costs, edges1, edges2) together.

    Per instance: the exact :func:`prefilter` returns the empty match when it proves it
    optimal, and otherwise gives the node pairs to model. The remaining instances are stacked
    block-diagonally into one LP relaxation (``linprog``, HiGHS). The LP separates into the
    blocks, so each block of the LP optimum is an optimum of its own relaxation, and a block
    that is integral is an optimal BLP solution ("lp_integral"): a relaxation's optimum that is
    feasible for the BLP is optimal for it. The non-integral blocks are stacked into one MILP
    (``milp``, HiGHS, ``cfg.time_limit_s`` and ``cfg.node_limit``); at a proven optimum of a separable problem every
    block is optimal ("milp_optimal", within ``cfg.mip_rel_gap`` of the stacked objective). If the MILP stops at a limit its blocks get
    status "time_limit" with the best solution found (the empty match if there is none), improved by
    :func:`improve_match`; a
    stacked MILP that hits a limit (also ``cfg.stack_node_limit``) is re-solved block by block, so that only the
    hard blocks are reported as "time_limit". Stacking turns hundreds of tiny solves into two, which
    removes HiGHS's per-call overhead (tens of ms for a MILP).

    ``solve_s`` of a result is its own preparation time plus an equal share of the LP and MILP
    it took part in. With ``cfg.prefilter`` False, neither bound nor reduction is applied.
    """
    results: list[MatchResult | _Problem] = [_prepare(C, edges1, edges2, cfg) for C, edges1, edges2 in problems]
    pending = [idx for idx, r in enumerate(results) if isinstance(r, _Problem)]  # each replaced by its result
    lp_share = 0.0
    if pending and cfg.lp_first:
        blocks, lp_share = _solve_lp([results[idx] for idx in pending], cfg)
        for idx, z in zip(pending, blocks):
            if z is not None:
                results[idx] = _result(z, results[idx], "lp_integral", lp_share, cfg)
        pending = [idx for idx, z in zip(pending, blocks) if z is None]
    if pending:
        for idx, r in zip(pending, _solve_milp([results[idx] for idx in pending], cfg, lp_share)):
            results[idx] = r
    return results


def match_costs(C: np.ndarray, edges1: np.ndarray, edges2: np.ndarray, cfg: MatchConfig) -> MatchResult:
    """Solve the matching BLP for one n1×n2 node-substitution cost matrix ``C`` (see :func:`match_batch`)."""
    return match_batch([(C, edges1, edges2)], cfg)[0]


def match_graphs(f1: np.ndarray, edges1: np.ndarray, f2: np.ndarray, edges2: np.ndarray,
                 cfg: MatchConfig) -> MatchResult:
    """Match source graph (f1: n1×D features, edges1: m1×2) into target (f2, edges2).

    Node costs are cosine distances; maps use row indices of ``f1`` and ``f2``.
    """
    return match_costs(cosine_distance(f1, f2), edges1, edges2, cfg)


def _component_edges(edges: np.ndarray, comps: Sequence[np.ndarray], n_nodes: int) -> list[np.ndarray]:
    """Edges of each component in component-local indices."""
    local = np.full(n_nodes, -1, dtype=np.int64)
    comp_of = np.full(n_nodes, -1, dtype=np.int64)
    for c, nodes in enumerate(comps):
        local[nodes] = np.arange(len(nodes))
        comp_of[nodes] = c
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    ce = comp_of[edges]
    if len(edges) and ((ce[:, 0] < 0) | (ce[:, 0] != ce[:, 1])).any():
        raise ValueError("an edge joins nodes of different components (or a node in no component)")
    return [local[edges[ce[:, 0] == c]] for c in range(len(comps))]


def _match_scene_pairs(pairs: Sequence[tuple[int, int]], graphs: dict[int, SceneGraph],
                       cfg: MatchConfig) -> list[PairMatch]:
    """All component pairs of the given scene pairs, both directions, solved as one batch (one task)."""
    cpu0 = time.process_time()
    meta, problems = [], []
    for a, b in pairs:
        for s, t in ((a, b), (b, a)):
            gs, gt = graphs[s], graphs[t]
            C = cosine_distance(gs.features, gt.features)
            es = _component_edges(gs.edges, gs.components, len(gs.features))
            et = _component_edges(gt.edges, gt.components, len(gt.features))
            for ci, src in enumerate(gs.components):
                for cj, tgt in enumerate(gt.components):
                    problems.append((C[src][:, tgt], es[ci], et[cj]))
                    meta.append((s, ci, t, cj, src, tgt, len(es[ci])))
    out = []
    for (s, ci, t, cj, src, tgt, n_edges), r in zip(meta, match_batch(problems, cfg)):
        r.node_map = {int(src[i]): int(tgt[k]) for i, k in r.node_map.items()}
        r.edge_map = [((int(src[i]), int(src[j])), (int(tgt[k]), int(tgt[l]))) for (i, j), (k, l) in r.edge_map]
        out.append(PairMatch(s, ci, t, cj, len(src), n_edges, r))
    share = (time.process_time() - cpu0) / max(1, len(out))
    for m in out:
        m.cpu_s = share
    return out


class _RecordingContext:
    """A multiprocessing context that keeps every process it makes, so their exit codes can be read after a
    ProcessPoolExecutor breaks."""

    def __init__(self) -> None:
        self._base = multiprocessing.get_context()
        self.processes: list = []

    def __getattr__(self, name: str):
        return getattr(self._base, name)

    def Process(self, *args, **kwargs):  # noqa: N802 (multiprocessing's name)
        p = self._base.Process(*args, **kwargs)
        self.processes.append(p)
        return p


def _limit_cpu(seconds: float) -> None:
    """Pool-worker initializer: the kernel stops this process (SIGXCPU) once it has used ``seconds`` of CPU."""
    soft = int(math.ceil(seconds + time.process_time()))
    _, hard = resource.getrlimit(resource.RLIMIT_CPU)
    resource.setrlimit(resource.RLIMIT_CPU, (soft if hard == resource.RLIM_INFINITY else min(soft, hard), hard))


def match_all(scenes: Sequence[SceneGraph], cfg: MatchConfig,
              executor: cf.Executor | None = None, progress: bool = True) -> list[PairMatch]:
    """Match every component of every scene against every component of every other scene.

    Both directions are solved (J is not symmetric). One executor task handles
    ``cfg.pairs_per_task`` unordered scene pairs as one :func:`match_batch`. Without
    ``executor``, a local process pool (:func:`selfseg.executor.make_executor`) with ``cfg.workers``
    processes is used (in-process when ``workers`` ≤ 1); any ``concurrent.futures.Executor`` (e.g.
    ``make_executor("ray")``) can be passed instead. Results are sorted by (src_scene, src_comp, tgt_scene, tgt_comp), so the output
    does not depend on scheduling.

    With ``cfg.cpu_budget_per_pair_s``, the budget is that × the number of scene pairs; the tasks' CPU seconds
    (measured in whichever process runs them) are summed as they finish, and MatchBudgetError is raised once the
    sum passes the budget. Without an ``executor`` the
    tasks then run in a pool of ``max(1, cfg.workers)`` processes whose CPU the kernel limits to the budget
    (RLIMIT_CPU), so one task that runs past the whole budget is stopped too; a given executor's tasks are
    only counted when they finish.
    """
    pairs = [(a, b) for a in range(len(scenes)) for b in range(a + 1, len(scenes))]
    step = max(1, cfg.pairs_per_task)
    tasks = [pairs[t:t + step] for t in range(0, len(pairs), step)]
    args = [(task, {s: scenes[s] for pair in task for s in pair}, cfg) for task in tasks]
    out: list[PairMatch] = []
    budget = None if cfg.cpu_budget_per_pair_s is None else cfg.cpu_budget_per_pair_s * len(pairs)
    per_pair = f"{cfg.cpu_budget_per_pair_s:g} s per scene pair" if budget is not None else ""
    bar = tqdm(total=len(pairs), desc="matching scene pairs", disable=not progress)

    def collect(part: list[PairMatch], n_pairs: int) -> None:
        out.extend(part)
        bar.update(n_pairs)
        if budget is not None and sum(m.cpu_s for m in out) > budget:
            raise MatchBudgetError(f"matching used more than its CPU budget of {budget:g} s ({per_pair}; "
                                   f"{bar.n} of {len(pairs)} scene pairs done)")

    if executor is None and cfg.workers <= 1 and budget is None:
        for a in args:
            collect(_match_scene_pairs(*a), len(a[0]))
    else:
        own = executor is None
        # a budget's own pool: the kernel also stops a worker whose one task runs past the whole budget
        ctx = _RecordingContext() if own and budget is not None else None
        ex = (cf.ProcessPoolExecutor(max(1, cfg.workers), ctx, initializer=_limit_cpu, initargs=(budget,))
              if ctx is not None else make_executor("local", workers=cfg.workers) if own else executor)
        try:
            futures = {ex.submit(_match_scene_pairs, *a): len(a[0]) for a in args}
            for fut in cf.as_completed(futures):
                try:
                    part = fut.result()
                except BrokenProcessPool:
                    if ctx is None:  # not the budget's own pool
                        raise
                    ex.shutdown(wait=True)  # its workers joined, so their exit codes are known
                    codes = sorted({p.exitcode for p in ctx.processes if p.exitcode})
                    if -signal.SIGXCPU not in codes:  # not the budget's doing: say how the workers ended
                        raise BrokenProcessPool(f"a matching worker ended abruptly (exit codes {codes})") from None
                    raise MatchBudgetError(f"matching used more than its CPU budget of {budget:g} s ({per_pair}) "
                                           f"in one task (the kernel stopped its worker; {bar.n} of {len(pairs)} "
                                           "scene pairs done)") from None
                collect(part, futures[fut])
        except BaseException:
            if own:
                ex.shutdown(wait=False, cancel_futures=True)
            raise
        if own:
            ex.shutdown()
    bar.close()
    out.sort(key=lambda m: (m.src_scene, m.src_comp, m.tgt_scene, m.tgt_comp))
    return out


def match_stats(matches: Sequence[PairMatch], cfg: MatchConfig) -> dict:
    """Counts of solve outcomes and solver time over component pairs, and the largest and median
    :meth:`MatchResult.limit_gap` of the solves stopped at a limit (None where none stopped or none had a bound);
    ``cfg``: the costs they were solved with."""
    status = [m.result.status for m in matches]
    n = len(matches)
    solved = n - status.count("prefiltered_empty")
    gaps = [m.result.limit_gap(m.n_src_nodes, m.n_src_edges, cfg) for m in matches if not m.result.proven_optimal]
    gaps = [g for g in gaps if g is not None]
    return {
        "component_pairs": n,
        "prefiltered": status.count("prefiltered_empty"),
        "prefilter_rate": status.count("prefiltered_empty") / n if n else 0.0,
        "solved": solved,
        "lp_integral": status.count("lp_integral"),
        "lp_integral_rate": status.count("lp_integral") / solved if solved else 0.0,
        "milp_optimal": status.count("milp_optimal"),
        "time_limit_hits": status.count("time_limit"),  # stopped at the time or the node limit
        "milp_nodes_max": max((m.result.milp_nodes for m in matches), default=0),
        "nonempty": sum(bool(m.result.node_map) for m in matches),
        "solver_s": sum(m.result.solve_s for m in matches),
        "cpu_s": sum(m.cpu_s for m in matches),  # CPU seconds of the tasks, in whichever processes ran them
        "limit_gap_max": max(gaps, default=None),
        "limit_gap_median": float(np.median(gaps)) if gaps else None,
    }

