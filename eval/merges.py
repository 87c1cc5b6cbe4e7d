"""Ground-truth scores of the matching step (Table II's ``ours-matching`` row): merge precision and
recall, and the φ1 cosine similarity of same- vs different-object segment pairs across scenes.

A segment's ground truth is the majority GT instance of its points (:func:`segment_instances`; 0 when
most of its points lie on no object). Within a scene two segments are the same object when their
instances are equal and non-zero; across scenes when their instances' ``obj_id`` (``scene_info.json``)
are equal. The matching step's merges come from its ``diagnostics.json``
(:func:`selfseg.method.pseudolabels.diagnostics`).
"""
from __future__ import annotations

from functools import partial

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components


def merge_same_instance(edges: np.ndarray, seg_inst: np.ndarray) -> np.ndarray:
    """Ground-truth merging, the most a matching step could merge: the group (int64, 0..G−1) of each
    segment when every graph edge (``edges`` E×2 segment pairs) whose two segments have the same non-zero
    majority instance (``seg_inst``, see :func:`segment_instances`) is merged; segments merge only
    through such edges, as matched subgraphs are connected."""
    inst = np.asarray(seg_inst, dtype=np.int64)
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    e = e[(inst[e[:, 0]] == inst[e[:, 1]]) & (inst[e[:, 0]] != 0)]
    n = len(inst)
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def relabel(labels: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Segment labels (any shape, −1 = none) → their groups' labels (``group[s]``), −1 kept."""
    labels = np.asarray(labels)
    return np.where(labels >= 0, np.asarray(group)[np.maximum(labels, 0)], -1)


def segment_instances(seg_labels: np.ndarray, gt_inst: np.ndarray, n_segments: int) -> np.ndarray:
    """Majority GT instance (int64) of each of ``n_segments`` segments; per point ``seg_labels`` (−1 = none)
    and ``gt_inst`` (0 = no object); 0 for a segment without points or with mostly unlabeled points."""
    seg, gt = np.asarray(seg_labels).ravel(), np.asarray(gt_inst).ravel().astype(np.int64)
    if seg.shape != gt.shape:
        raise ValueError(f"{len(seg)} segment labels but {len(gt)} ground-truth labels")
    keep = seg >= 0
    n_inst = int(gt.max(initial=0)) + 1
    counts = np.bincount(seg[keep] * n_inst + gt[keep], minlength=n_segments * n_inst).reshape(n_segments, n_inst)
    return counts.argmax(axis=1).astype(np.int64)


def summary(x) -> dict:
    """n, quartiles, median and max of a sample (None when empty)."""
    x = np.asarray(x, dtype=np.float64)
    if not len(x):
        return {"n": 0, "q25": None, "median": None, "q75": None, "max": None}
    q25, med, q75 = np.quantile(x, [0.25, 0.5, 0.75])
    return {"n": int(len(x)), "q25": float(q25), "median": float(med), "q75": float(q75), "max": float(x.max())}


def _ratio(a: int, b: int) -> float | None:
    return a / b if b else None


def same_object(seg_inst: dict[str, np.ndarray], inst_obj: dict[str, dict[int, int]], a: str, i: int, b: str,
                k: int) -> bool:
    """Segment i of scene a and segment k of scene b show one GT object: the same instance within a scene,
    instances of one obj_id across scenes (background, instance 0, is never one)."""
    ia, ib = int(seg_inst[a][i]), int(seg_inst[b][k])
    if ia == 0 or ib == 0:
        return False
    return ia == ib if a == b else inst_obj[a].get(ia, -1) == inst_obj[b].get(ib, -2)


def merge_scores(diag: dict, seg_inst: dict[str, np.ndarray], inst_obj: dict[str, dict[int, int]],
                 seg_object: dict[str, np.ndarray], seg_edges: dict[str, np.ndarray]) -> dict:
    """Precision and recall of the merges.

    ``seg_inst``: majority instance per segment, per scene; ``inst_obj``: instance → obj_id per scene;
    ``seg_object``: the pseudo-label object of each segment after merging; ``seg_edges``: the segment
    graph's adjacent pairs (E×2) per scene.

    - within: precision = share of the merge edges (``diag["merges"]["within"]``) joining two segments of
      the same instance; recall = share of the adjacent same-instance segment pairs (what an ideal
      matching step would join) that ended up in one pseudo-label object;
    - across: precision = share of the matched cross-scene segment pairs that carried merges
      (``diag["merges"]["across"]``) whose instances are the same object (obj_id); recall = share of
      the segments whose object appears in another scene that take part in at least one correct pair.
    """
    same = partial(same_object, seg_inst, inst_obj)

    w_pairs = [(s, i, j) for s, edges in diag["merges"]["within"].items() for i, j in edges]
    w_ok = sum(same(s, i, s, j) for s, i, j in w_pairs)
    should = [(s, int(i), int(j)) for s, e in seg_edges.items() for i, j in np.asarray(e).reshape(-1, 2)
              if same(s, int(i), s, int(j))]
    done = sum(int(seg_object[s][i] == seg_object[s][j]) for s, i, j in should)
    across = [tuple(x) for x in diag["merges"]["across"]]
    ok_across = [(a, i, b, k) for a, i, b, k in across if same(a, i, b, k)]
    objs = {s: {inst_obj[s][int(x)] for x in v if int(x) in inst_obj[s]} for s, v in seg_inst.items()}
    reappearing = {(s, i) for s, v in seg_inst.items() for i, x in enumerate(v)
                   if int(x) in inst_obj[s] and any(inst_obj[s][int(x)] in objs[t] for t in objs if t != s)}
    matched = {(a, i) for a, i, _, _ in ok_across} | {(b, k) for _, _, b, k in ok_across}
    return {"within": {"merges": len(w_pairs), "correct": w_ok, "precision": _ratio(w_ok, len(w_pairs)),
                       "same_instance_adjacent": len(should), "merged": done, "recall": _ratio(done, len(should))},
            "across": {"pairs": len(across), "correct": len(ok_across), "precision": _ratio(len(ok_across), len(across)),
                       "reappearing_segments": len(reappearing), "matched_segments": len(matched & reappearing),
                       "recall": _ratio(len(matched & reappearing), len(reappearing))}}


def cosine_by_object(features: dict[str, np.ndarray], seg_inst: dict[str, np.ndarray],
                     inst_obj: dict[str, dict[int, int]]) -> dict:
    """Cosine similarity of the segment features (rows = segment ids) of every segment pair in two
    different scenes, both on an object: {"same_object": summary, "different_object": summary}."""
    ids = sorted(features)
    feats, objs = {}, {}
    for s in ids:
        f = np.asarray(features[s], dtype=np.float64)
        on = np.array([int(x) in inst_obj[s] for x in seg_inst[s]], dtype=bool)
        feats[s] = f[on] / np.maximum(np.linalg.norm(f[on], axis=1, keepdims=True), 1e-12)
        objs[s] = np.array([inst_obj[s][int(x)] for x in seg_inst[s][on]], dtype=np.int64)
    same, diff = [], []
    for n, a in enumerate(ids):
        for b in ids[n + 1:]:
            cos = feats[a] @ feats[b].T
            eq = objs[a][:, None] == objs[b][None, :]
            same.append(cos[eq])
            diff.append(cos[~eq])
    cat = lambda x: np.concatenate(x) if x else np.zeros(0)  # noqa: E731
    return {"same_object": summary(cat(same)), "different_object": summary(cat(diff))}
