"""Diagnostic, not a test: what pruning's criterion 3 (isolation) drops, scored by ground truth.

    .venv/bin/python experiments/bench_isolation.py --data runs/dev7/data --config configs/ours-calibrated.yaml
        --results runs/dev7/levers-ours --run ours@wit02 [--folds 0] [--json experiments/results/isolation.json]

For each fold's pseudo stage (RESULTS/work/<run>/<dataset>/fold<k>/):

- **unmerged pairs**: the adjacent same-instance segment pairs of its training videos that did not end in one
  pseudo-label object, each by the best fate of a match that mapped the pair as an edge (a correct match
  first, then the reasons of its two node pairs), or "never mapped";
- **victims**: every match dropped by isolation, by whether all its node pairs are one object, whether its
  witness's are, and the witness's size;
- **cover**: for each victim, the smallest share of an extra target segment's points (the victim's target
  nodes beyond the witness's) within ``dist_thresh_m`` of the witness's source component under the witness's
  registration, split by whether every extra segment is the same GT instance as the witness's target nodes.
  This is the quantity ``PruneConfig.isolation_cover`` thresholds.

Reads ground truth: a diagnostic for development data. Segments, reconstructions and GT point labels come from
``evaluate3d``'s stage layout under RESULTS (as in ``bench_fold_merges.py``; point counts are checked).
"""
from __future__ import annotations

from collections import Counter
from functools import partial
from pathlib import Path

import numpy as np
from common import fold_bench_inputs, fold_bench_parser, pseudo_stage, save, segment_clouds_of

from selfseg.dataset import Dataset
from selfseg.eval.merges import same_object
from selfseg.eval.table2 import merge_inputs
from selfseg.fileio import read_json
from selfseg.method.pipeline import LABELS_NPY, OursConfig
from selfseg.method.pseudolabels import MATCHES_JSON
from selfseg.method.registration import precision_recall


def edge_fates(matches: list[dict], same) -> dict[tuple[str, int, int], list[tuple[bool, tuple[str, ...]]]]:
    """(scene, i, j) with i < j → (match all-correct on the edge, its two node pairs' reasons) per mapping match."""
    fates: dict = {}
    for m in matches:
        src_reason = {p["src"]: p["reason"] for p in m["pairs"]}
        for (i, j), (k, l) in m["edge_map"]:
            fate = (same(m["src_scene"], i, m["tgt_scene"], k) and same(m["src_scene"], j, m["tgt_scene"], l),
                    tuple(sorted({src_reason[i], src_reason[j]})))
            fates.setdefault((m["src_scene"], min(i, j), max(i, j)), []).append(fate)
            fates.setdefault((m["tgt_scene"], min(k, l), max(k, l)), []).append(fate)
    return fates


def fold_rows(fold_dir: Path, seg, gt_inst, dataset: Dataset, config: OursConfig) -> dict:
    stage = pseudo_stage(fold_dir)
    record = read_json(stage / MATCHES_JSON)
    matches = record["matches"]
    scenes = {s.video_id: s for s in seg.scenes if s.video_id in record["scenes"]}
    point_obj = {vid: np.load(stage / LABELS_NPY.format(video_id=vid)) for vid in scenes}
    for vid, s in scenes.items():
        if point_obj[vid].shape != np.shape(s.graph.labels):
            raise SystemExit(f"bench_isolation: {stage}: video {vid}'s reconstruction differs from evaluate3d's")
    seg_inst, inst_obj, seg_object, edges = merge_inputs(dataset, scenes.values(), point_obj, gt_inst)
    same = partial(same_object, seg_inst, inst_obj)
    pc = config.pseudo.prune
    clouds = {vid: segment_clouds_of(s, pc) for vid, s in scenes.items()}

    should = [(s, int(i), int(j)) for s, e in edges.items() for i, j in np.asarray(e).reshape(-1, 2)
              if same(s, int(i), s, int(j))]
    fates = edge_fates(matches, same)
    unmerged = Counter()
    for s, i, j in should:
        if seg_object[s][i] == seg_object[s][j]:
            continue
        fs = fates.get((s, min(i, j), max(i, j)))
        if not fs:
            unmerged["never mapped"] += 1
        else:
            ok, reasons = min(fs, key=lambda f: (not f[0], f[1]))
            unmerged[f"{'+'.join(reasons)} ({'correct match' if ok else 'wrong matches only'})"] += 1

    victims, cover = Counter(), {"extras_same_instance": [], "extras_other": []}
    for m in matches:
        if m.get("isolation_witness") is None:
            continue
        w = matches[m["isolation_witness"]]
        ok = all(same(m["src_scene"], a, m["tgt_scene"], b) for a, b in m["node_map"])
        w_ok = all(same(w["src_scene"], a, w["tgt_scene"], b) for a, b in w["node_map"])
        victims[f"victim {'correct' if ok else 'wrong'}, witness {'correct' if w_ok else 'wrong'}, "
                f"witness size {len(w['node_map'])}"] += 1
        t = m["tgt_scene"]
        witnessed = [b for _, b in w["node_map"]]
        extra = [b for _, b in m["node_map"] if b not in witnessed]
        src = np.concatenate([clouds[w["src_scene"]][a] for a, _ in w["node_map"]])
        T = np.asarray(w["registration"]["T_tgt_src"])
        c = min(precision_recall(src, clouds[t][b], T, pc.dist_thresh_m)[1] for b in extra)
        one = all(same(t, b, t, witnessed[0]) for b in extra)
        cover["extras_same_instance" if one else "extras_other"].append(round(float(c), 3))
    return {"fold": fold_dir.name, "videos": sorted(scenes), "adjacent_same_instance_pairs": len(should),
            "unmerged": dict(unmerged.most_common()), "victims": dict(sorted(victims.items())),
            "cover": {k: sorted(v) for k, v in cover.items()}, "dist_thresh_m": pc.dist_thresh_m}


def main(argv: list[str] | None = None) -> int:
    args = fold_bench_parser(__doc__, "experiments/results/isolation.json").parse_args(argv)
    inputs = fold_bench_inputs("bench_isolation", args)
    if inputs is None:
        return 2
    dataset, config, seg, _, gt_inst, folds = inputs
    rows = [{"run": run, **fold_rows(f, seg, gt_inst, dataset, config)} for run, f in folds]
    for r in rows:
        print(f"{r['run']} {r['fold']}: {sum(r['unmerged'].values())} of {r['adjacent_same_instance_pairs']} "
              "adjacent same-instance pairs unmerged")
        for what in ("unmerged", "victims"):
            for k, n in r[what].items():
                print(f"  {what:<9} {n:>4}  {k}")
        for k, v in r["cover"].items():
            print(f"  cover of extras, {k} ({len(v)}): {v}")
    save(args.json, "what criterion 3 drops, by ground truth (experiments/bench_isolation.py)", args.data, dataset,
         args.config, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
