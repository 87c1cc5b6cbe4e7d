"""Diagnostic, not a test: on the component pairs whose MILP stops at the node limit (cluttered piles), how far
from optimal is the match matching returns there (HiGHS's incumbent, improved by ``matching.improve_match``)?

    .venv/bin/python experiments/bench_matching_polish.py --data DIR --config configs/ours-cluttered.yaml
        [--set k=v ...] --results OUT --features PHI1_FEATURES_DIR --name NAME [--node-limit 12]
        [--long-node-limit 2000 --long-time-limit-s 120] [--max-pairs N] [--dump DIR]
        [--json experiments/results/matching_polish.json]

OUT is a results folder whose stage cache holds the videos' over-segmentation for the config (computed into it
otherwise); PHI1_FEATURES_DIR holds φ1's feature per segment (``<video>.npy``) of one fold's training videos, the
videos matched (as ``ours`` does: every component of every scene into every component of every other, both
directions). Ground truth is not read. Each instance goes through matching's pre-filter and LP; the non-integral
ones are solved alone as a MILP at ``--node-limit``, and for each stopped at the limit the row holds: J_empty,
HiGHS's lower bound, the returned match's J, and the MILP's J, bound and node count with the long limits
(``--long-node-limit 0``: not run). The gap of a J is
(J − bound) / (J_empty − bound), the bound being the best of the two MILPs'.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from common import phi1_features, save

from selfseg.config import load_config
from selfseg.dataset import Dataset
from selfseg.eval.table2 import segment_scenes
from selfseg.method.matching import (_Problem, _component_edges, _prepare, _solve_lp, _solve_milp, cosine_distance,
                                     empty_match_cost)
from selfseg.method.pipeline import OursConfig


def instances(graphs: list[tuple[str, np.ndarray, np.ndarray, list[np.ndarray]]]):
    """(name, C, source edges, target edges) of every component pair of every ordered scene pair."""
    for a, (sa, fa, ea, ca) in enumerate(graphs):
        for b, (sb, fb, eb, cb) in enumerate(graphs):
            if a == b:
                continue
            C = cosine_distance(fa, fb)
            la, lb = _component_edges(ea, ca, len(fa)), _component_edges(eb, cb, len(fb))
            for i, src in enumerate(ca):
                for j, tgt in enumerate(cb):
                    yield f"{sa}:{i}->{sb}:{j}", C[src][:, tgt], la[i], lb[j]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True)
    p.add_argument("--config", required=True)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a config override (repeatable)")
    p.add_argument("--results", required=True, help="the results folder whose stage cache holds the segmentations")
    p.add_argument("--features", required=True, help="a φ1 features folder (<video>.npy per training video)")
    p.add_argument("--name", required=True)
    p.add_argument("--node-limit", type=int, default=12)
    p.add_argument("--long-node-limit", type=int, default=2000)
    p.add_argument("--long-time-limit-s", type=float, default=120.0)
    p.add_argument("--dump", help="write each instance that needs a MILP to DIR/<pair>.npz (C, e1, e2) and stop")
    p.add_argument("--max-pairs", type=int, default=0, help="stop after this many stopped pairs (0: all)")
    p.add_argument("--json", default="experiments/results/matching_polish.json")
    args = p.parse_args(argv)
    dataset = Dataset(args.data)
    config = load_config(OursConfig, args.config, args.set)
    seg = segment_scenes(dataset, config, Path(args.results), ("lccp+symseg",))
    feats = phi1_features("bench_matching_polish", args.features, seg.scenes)
    if feats is None:
        return 2
    videos = sorted(feats)
    graphs = [(s.video_id, feats[s.video_id], np.asarray(s.graph.edges, np.int64).reshape(-1, 2),
               [np.asarray(c, np.int64) for c in s.graph.components()]) for s in seg.scenes if s.video_id in feats]
    cfg = dataclasses.replace(config.pseudo.match, node_limit=args.node_limit, time_limit_s=600.0)
    long_cfg = dataclasses.replace(cfg, node_limit=args.long_node_limit, time_limit_s=args.long_time_limit_s)
    probs = [(name, _prepare(C, e1, e2, cfg)) for name, C, e1, e2 in instances(graphs)]
    hard = [(n, q) for n, q in probs if isinstance(q, _Problem)]
    blocks, _ = _solve_lp([q for _, q in hard], cfg)
    hard = [(n, q) for (n, q), z in zip(hard, blocks) if z is None]
    print(f"{args.name}: {len(probs)} component pairs, {len(hard)} need a MILP", flush=True)
    if args.dump:
        Path(args.dump).mkdir(parents=True, exist_ok=True)
        for name, q in hard:
            np.savez(Path(args.dump) / f"{name.replace(':', '_').replace('->', '-')}.npz", C=q.C, e1=q.e1, e2=q.e2)
        return 0
    rows = []
    for name, q in hard:
        t0 = time.process_time()
        r = _solve_milp([q], cfg, 0.0)[0]
        milp_s = time.process_time() - t0
        if r.proven_optimal:
            continue
        j_empty = empty_match_cost(len(q.C), len(q.e1), cfg)
        row = {"pair": name, "n1": int(q.C.shape[0]), "n2": int(q.C.shape[1]), "vars": len(q.c), "j_empty": j_empty,
               "bound": r.cost_bound, "j_milp": r.cost, "milp_cpu_s": milp_s}
        if args.long_node_limit:
            t0 = time.process_time()
            r2 = _solve_milp([q], long_cfg, 0.0)[0]
            row.update(j_long_milp=r2.cost, long_bound=r2.cost_bound if not r2.proven_optimal else r2.cost,
                       long_status=r2.status, long_nodes=r2.milp_nodes, long_cpu_s=time.process_time() - t0)
        bound = max(b for b in (row["bound"], row.get("long_bound")) if b is not None)
        for key in ("j_milp", "j_long_milp"):
            if key in row:
                row[key.replace("j_", "gap_")] = (row[key] - bound) / (j_empty - bound) if j_empty > bound else 0.0
        rows.append(row)
        print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()), flush=True)
        if len(rows) == args.max_pairs:
            break
    summary = {k: {"median": float(np.median([r[k] for r in rows])), "max": float(np.max([r[k] for r in rows]))}
               for k in ("gap_milp", "gap_long_milp")
               if rows and k in rows[0]}
    print(summary)
    save(args.json, "the node limit's incumbents against local search from them and a long MILP, on the pairs "
         "stopped at the limit", args.data, dataset, args.config,
         [{"name": args.name, "sets": args.set, "videos": videos, "node_limit": args.node_limit,
           "long_node_limit": args.long_node_limit, "long_time_limit_s": args.long_time_limit_s,
           "summary": summary, "pairs": rows}])
    return 0


if __name__ == "__main__":
    sys.exit(main())
