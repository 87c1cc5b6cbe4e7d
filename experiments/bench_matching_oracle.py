"""Diagnostic, not a test: is it φ1 or matching + pruning that keeps graph matching from merging?

    .venv/bin/python experiments/bench_matching_oracle.py --data DIR --out RESULTS [--config FILE] [--set k=v ...]
                                                    [--json experiments/results/matching_oracle.json]

Runs the pseudo-label step (``ours`` and ``v3_no_pruning``) on the scenes of an ``evaluate3d`` run
(``--out`` is its results folder: the cached reconstructions, over-segments and φ1 are reused) twice:
with the φ1 segment features, and with *identity-oracle* features that know each segment's object from
ground truth: ``normalize([onehot(obj_id), ε · φ1])`` with ε = 0.3. Two segments of the same object then
have cosine (1 + ε² cos φ1) / (1 + ε²) ≥ .9 whenever their φ1 cosine is ≥ −0.01, so the paper's
c_del = .1 admits them, while segments of different objects stay below ε² / (1 + ε²) = .083; φ1 still
tells the parts of one object apart. Segments mostly off every object keep φ1 alone.

Prints and writes how many adjacent same-instance segment pairs there are, and how many belong to an object
that is also split into adjacent segments in another scene (only those can be merged: a merge needs a
mapped edge); then per (features, mode): merges, their precision and recall against the adjacent
same-instance segment pairs (:func:`selfseg.eval.merges.merge_scores`), the pruning outcomes, and
Table II IoU of the resulting pseudo-labels; plus the ``lccp+symseg`` and ``gt-merging`` rows. Last, for the
pruned runs, min(precision, recall) of every registered node pair, same-object vs different-object by
ground truth, and how many of each would pass criterion 2 at T2 = .9 … .5 (what T2 can and cannot separate).
"""
from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from selfseg.config import load_config
from selfseg.dataset import Dataset
from selfseg.eval.merges import merge_same_instance, relabel, segment_instances, summary
from selfseg.eval.points import GT_MAX_DIST_M, PointsEvaluator, gt_point_labels
from selfseg.eval.table2 import alignment, matching_record, segment_scenes
from selfseg.fileio import read_json, write_json
from selfseg.method.pipeline import OursConfig, Segmentations3D
from selfseg.method.pseudolabels import DIAGNOSTICS_JSON, MATCHES_JSON, SceneData, make_pseudo_labels
from selfseg.poses import transform_points

EPS = 0.3  # weight of φ1 in the identity-oracle features (see the module docstring)
T2_GRID = (0.9, 0.8, 0.7, 0.6, 0.5)  # criterion-2 thresholds at which the registered node pairs are counted


def oracle_features(features: np.ndarray, seg_inst: np.ndarray, inst_obj: dict[int, int], obj_ids: list[int]
                    ) -> np.ndarray:
    """S×(n_obj + D) unit features: one-hot of each segment's object (none for instance 0) beside ε·φ1."""
    onehot = np.zeros((len(features), len(obj_ids)))
    for s, k in enumerate(seg_inst):
        if int(k) in inst_obj:
            onehot[s, obj_ids.index(inst_obj[int(k)])] = 1.0
    f = np.concatenate([onehot, EPS * np.asarray(features, dtype=np.float64)], axis=1)
    return f / np.linalg.norm(f, axis=1, keepdims=True)


def matchable_pairs(edges: dict[str, np.ndarray], seg_inst: dict[str, np.ndarray], inst_obj: dict[str, dict[int, int]]
                    ) -> tuple[int, int]:
    """(adjacent same-instance segment pairs, those whose object is also split into adjacent segments in
    another scene): only the latter have an edge that a match can map, which every merge needs."""
    split = {}  # scene → objects with an adjacent same-instance segment pair there
    pairs = []
    for v, e in edges.items():
        for i, j in np.asarray(e).reshape(-1, 2):
            k = int(seg_inst[v][i])
            if k and k == int(seg_inst[v][j]) and k in inst_obj[v]:
                pairs.append((v, inst_obj[v][k]))
                split.setdefault(v, set()).add(inst_obj[v][k])
    ok = sum(any(o in objs for w, objs in split.items() if w != v) for v, o in pairs)
    return len(pairs), ok


def registered_pairs(matches: dict, seg_inst: dict[str, np.ndarray], inst_obj: dict[str, dict[int, int]]) -> dict:
    """min(precision, recall) of every registered node pair of ``matches.json``, split by ground truth into
    same-object and different-object pairs, and how many of each pass criterion 2 at each T2 of T2_GRID."""
    def obj(scene: str, seg: int) -> int | None:
        return inst_obj[scene].get(int(seg_inst[scene][seg]))

    out: dict[str, list[float]] = {"same_object": [], "different_object": []}
    for m in matches["matches"]:
        for pair in m["pairs"]:
            if pair["precision"] is None:
                continue
            a, b = obj(m["src_scene"], pair["src"]), obj(m["tgt_scene"], pair["tgt"])
            out["same_object" if a is not None and a == b else "different_object"].append(
                min(pair["precision"], pair["recall"]))
    return {k: {"summary": summary(v), "passing": {str(t): int(np.sum(np.asarray(v) >= t)) for t in T2_GRID}}
            for k, v in out.items()}


def table2_iou(dataset: Dataset, seg: Segmentations3D, aligned: dict, labels: dict[str, np.ndarray]) -> float:
    """Table II IoU of per-point labels (−1 = none) over every video."""
    ev = PointsEvaluator(dataset, GT_MAX_DIST_M)
    for s in seg.scenes:
        ev.process(s.video_id, s.recon.points_w, labels[s.video_id] + 1, aligned[s.video_id][0])
    return float(ev.evaluate()["metrics"]["IoU"])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True)
    p.add_argument("--out", required=True, help="the evaluate3d results folder whose stages are reused")
    p.add_argument("--config", default=None)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--json", default="experiments/results/matching_oracle.json")
    args = p.parse_args(argv)
    dataset = Dataset(args.data)
    config = load_config(OursConfig, args.config, args.set)
    seg = segment_scenes(dataset, config, Path(args.out), ("lccp+symseg", "ours-matching"))
    aligned = {s.video_id: alignment(s.recon, dataset.labeled(s.video_id)) for s in seg.scenes}
    gt_inst = {s.video_id: gt_point_labels(transform_points(s.recon.points_w, aligned[s.video_id][0]), dataset,
                                           s.video_id, GT_MAX_DIST_M) for s in seg.scenes}
    inst_obj = {s.video_id: dataset.labeled(s.video_id).instance_to_object() for s in seg.scenes}
    obj_ids = sorted({o for m in inst_obj.values() for o in m.values()})
    seg_inst = {s.video_id: segment_instances(s.graph.labels, gt_inst[s.video_id], s.graph.n_segments)
                for s in seg.scenes}

    n_pairs, n_matchable = matchable_pairs({s.video_id: s.graph.edges for s in seg.scenes}, seg_inst, inst_obj)
    print(f"adjacent same-instance segment pairs: {n_pairs}; of them, of an object also split in another scene: "
          f"{n_matchable}")
    rows = []
    base = {s.video_id: s.labels["lccp+symseg"] for s in seg.scenes}
    gt_merged = {}
    for s in seg.scenes:
        gt_merged[s.video_id] = relabel(s.graph.labels, merge_same_instance(s.graph.edges, seg_inst[s.video_id]))
    rows.append({"features": "–", "mode": "lccp+symseg", "IoU": table2_iou(dataset, seg, aligned, base)})
    rows.append({"features": "ground truth", "mode": "gt-merging", "IoU": table2_iou(dataset, seg, aligned, gt_merged)})
    feats = {"phi1": {s.video_id: s.features for s in seg.scenes},
             "identity-oracle": {s.video_id: oracle_features(s.features, seg_inst[s.video_id], inst_obj[s.video_id],
                                                             obj_ids) for s in seg.scenes}}
    for name, f in feats.items():
        for mode in ("ours", "v3_no_pruning"):
            cfg = replace(config.pseudo, mode=mode)
            scenes = [SceneData(s.video_id, s.recon.points_w, s.graph, f[s.video_id]) for s in seg.scenes]
            with tempfile.TemporaryDirectory() as tmp:
                labels = make_pseudo_labels(scenes, cfg, tmp, progress=False)
                diag = read_json(Path(tmp) / DIAGNOSTICS_JSON)
                matches = read_json(Path(tmp) / MATCHES_JSON)
            scored = Segmentations3D([replace(s, labels={"ours-matching": labels[s.video_id]}, features=f[s.video_id])
                                      for s in seg.scenes], diag, {})
            rec = matching_record(dataset, scored, gt_inst)
            w = rec["gt"]["within"]
            rows.append({"features": name, "mode": mode, "IoU": table2_iou(dataset, seg, aligned, labels),
                         "merges": rec["totals"]["merges"], "merge_precision": w["precision"],
                         "merge_recall": w["recall"], "same_instance_adjacent": w["same_instance_adjacent"],
                         "matching": rec["matching"], "pruning": rec["pruning"],
                         "cosine": rec["gt"]["cosine"]})
            if mode == "ours":
                rows[-1]["registered_pairs"] = registered_pairs(matches, seg_inst, inst_obj)
    f3 = lambda x: "–" if x is None else f"{x:.3f}"  # noqa: E731
    print(f"{'features':>16} {'mode':>14} {'IoU':>6} {'merges':>6} {'P':>6} {'R':>6}  pruning (matches by outcome)")
    for r in rows:
        print(f"{r['features']:>16} {r['mode']:>14} {f3(r['IoU']):>6} {r.get('merges', '–'):>6} "
              f"{f3(r.get('merge_precision')):>6} {f3(r.get('merge_recall')):>6}  "
              f"{r.get('pruning', {}).get('matches_by_outcome', '')}")
    print("registered node pairs (criterion 2), min(P, R) by ground truth; passing at T2 =", T2_GRID)
    for r in rows:
        for k, v in r.get("registered_pairs", {}).items():
            q = v["summary"]
            print(f"{r['features']:>16} {k:>16}: n {q['n']:>4}, median {f3(q['median'])}, q75 {f3(q['q75'])}, "
                  f"max {f3(q['max'])}; passing {list(v['passing'].values())}")
    write_json(args.json, {"data": str(args.data), "dataset_hash": dataset.content_hash(), "eps": EPS,
                           "config_overrides": args.set, "same_instance_adjacent": n_pairs,
                           "matchable": n_matchable, "rows": rows})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
