"""Diagnostic, not a test: would cutting the segment graph's weak edges split a cluttered scene's piles into
components small enough for matching, and how many same-object edges would the cut lose?

    .venv/bin/python experiments/bench_pile_split.py --data DIR --config configs/ours-cluttered.yaml [--set k=v ...]
        --results OUT --features PHI1_FEATURES_DIR --name NAME [--cue phi1|contact] [--taus 0.5,0.7,0.9]
        [--json experiments/results/pile_split.json]

On a development dataset (it reads the ground truth). OUT is a results folder whose stage cache holds the
videos' reconstructions (``evaluate`` / ``evaluate3d --out OUT``); the over-segmentation of the config (with the
``--set`` overrides) is read from it or computed into it. PHI1_FEATURES_DIR holds one fold's φ1 feature per
segment (``<video>.npy``, the ``features-*`` folder of a φ1 stage), for that fold's training videos, which are
the videos measured. An edge is kept when its cue is at least τ: ``phi1``, the cosine of its two segments' φ1
features (a segment never seen by φ1 has a zero feature, so its edges are cut); ``contact``, the number of
boundary point pairs behind it (:func:`~selfseg.method.segment_graph.boundary_pairs`, growing with the length of
the shared boundary; touching objects meet in small patches). Per τ: the components' sizes (matching's problem
size grows with the product of two components' sizes), the share of same-object edges kept (each cut one is a
merge matching can no longer make within a scene) and of different-object edges cut, and the share of
components that hold more than one object.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

from common import phi1_features, save

from selfseg.config import load_config
from selfseg.dataset import Dataset
from selfseg.eval.merges import segment_instances, summary
from selfseg.eval.points import GT_MAX_DIST_M
from selfseg.eval.table2 import labeled_scenes
from selfseg.fileio import read_json
from selfseg.method.pipeline import OursConfig
from selfseg.method.segment_graph import SegmentGraph, boundary_pairs


def phi1_cosine(feats: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Cosine of the φ1 features (S×D) of each edge's two segments (0 where one is zero: never seen)."""
    f = feats / np.maximum(np.linalg.norm(feats, axis=1, keepdims=True), 1e-12)
    return np.einsum("ij,ij->i", f[edges[:, 0]], f[edges[:, 1]]) if len(edges) else np.zeros(0)


def contact(points: np.ndarray, graph: SegmentGraph) -> np.ndarray:
    """Boundary point pairs behind each edge of ``graph`` (a :class:`SegmentGraph` over ``points``, N×3 m)."""
    pairs, counts = np.unique(boundary_pairs(points, graph.labels, graph.adjacency_radius_m), axis=0,
                              return_counts=True)
    index = {(int(a), int(b)): int(c) for (a, b), c in zip(pairs, counts)}
    return np.array([index[(int(a), int(b))] for a, b in graph.edges], np.float64)


def split_row(scenes: list[tuple[SegmentGraph, np.ndarray, np.ndarray]], tau: float | None) -> dict:
    """The measures at one τ (None: no cut) over ``scenes``: (segment graph, the cue per edge, GT instance per
    segment)."""
    sizes, largest, kept_same, n_same, cut_diff, n_diff, mixed, n_comp = [], [], 0, 0, 0, 0, 0, 0
    for graph, cue, inst in scenes:
        edges = np.asarray(graph.edges).reshape(-1, 2)
        keep = np.ones(len(edges), bool) if tau is None else cue >= tau
        same = (inst[edges[:, 0]] == inst[edges[:, 1]]) & (inst[edges[:, 0]] > 0)
        kept_same += int((keep & same).sum())
        n_same += int(same.sum())
        cut_diff += int((~keep & ~same).sum())
        n_diff += int((~same).sum())
        comps = dataclasses.replace(graph, edges=edges[keep]).components()
        sizes += [len(c) for c in comps]
        largest.append(len(comps[0]))
        mixed += sum(len(set(inst[c].tolist()) - {0}) > 1 for c in comps)
        n_comp += len(comps)
    return {"tau": tau, "components": n_comp, "component_size": summary(sizes), "largest_per_scene": summary(largest),
            "same_object_edges_kept": kept_same / max(n_same, 1), "same_object_edges": n_same,
            "different_object_edges_cut": cut_diff / max(n_diff, 1), "different_object_edges": n_diff,
            "components_with_several_objects": mixed / max(n_comp, 1)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="a development dataset (reads its ground truth)")
    p.add_argument("--config", required=True)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a config override (repeatable)")
    p.add_argument("--results", required=True, help="the results folder whose stage cache holds the reconstructions")
    p.add_argument("--features", required=True, help="a φ1 stage's features-* folder (<video>.npy per video)")
    p.add_argument("--name", required=True, help="the row's name (the setting measured)")
    p.add_argument("--cue", choices=("phi1", "contact"), default="phi1", help="what an edge is kept by")
    p.add_argument("--taus", default="0.3,0.5,0.6,0.7,0.8,0.9", help="thresholds on the cue")
    p.add_argument("--json", default="experiments/results/pile_split.json")
    args = p.parse_args(argv)
    dataset = Dataset(args.data)
    config = load_config(OursConfig, args.config, args.set)
    seg, _, gt_inst = labeled_scenes(dataset, config, Path(args.results), ("lccp+symseg",), None, GT_MAX_DIST_M,
                                     None, gt_labels=True)
    features = phi1_features("bench_pile_split", args.features, seg.scenes)
    if features is None:
        return 2
    videos = sorted(features)
    scenes = []
    for s in seg.scenes:
        if s.video_id not in features:
            continue
        feats = features[s.video_id]
        inst = segment_instances(s.graph.labels, gt_inst[s.video_id], s.graph.n_segments)
        cue = (phi1_cosine(feats, np.asarray(s.graph.edges).reshape(-1, 2)) if args.cue == "phi1"
               else contact(s.recon.points_w, s.graph))
        scenes.append((s.graph, cue, inst))
    rows = [{"name": args.name, "cue": args.cue, "sets": args.set, "videos": videos, **split_row(scenes, t)}
            for t in (None, *(float(x) for x in args.taus.split(",")))]
    print(f"{args.name}: {len(scenes)} scenes")
    print("   tau  comps  largest/scene (median, max)  same-object edges kept  diff-object edges cut  mixed comps")
    for r in rows:
        t = "none" if r["tau"] is None else f"{r['tau']:g}"
        big = r["largest_per_scene"]
        print(f"{t:>6} {r['components']:>6}  {big['median']:>10.0f} {big['max']:>6.0f}"
              f"  {r['same_object_edges_kept']:>22.3f}  {r['different_object_edges_cut']:>21.3f}"
              f"  {r['components_with_several_objects']:>11.3f}")
    earlier = []
    if Path(args.json).is_file():
        earlier = [r for r in read_json(args.json).get("rows", [])
                   if (r.get("name"), r.get("cue", "phi1")) != (args.name, args.cue)]
    save(args.json, "segment-graph edges cut where a cue (φ1 cosine, shared boundary) is weak: pile components "
         "against lost same-object edges", args.data, dataset, args.config, earlier + rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
