"""Per-frame instance segmentation metrics: the paper's P/R/IoU and the UOIS Overlap/Boundary P/R/F.

Everything is scored over ground-truth foreground only (``gt > 0``): predicted ids outside it
are ignored, foreground pixels predicted as 0 count as missed. Segment ids are arbitrary.

* **Paper metrics** (``P``, ``R``, ``IoU``; see ``shared/paper.md`` [selfseg]): predicted and
  ground-truth segments are matched by the Hungarian algorithm with cost 1 − IoU. Each matched
  ground-truth object scores |P∩G|/|P|, |P∩G|/|G| and IoU; an unmatched one, or one whose pair
  has zero overlap, scores 0 on all three. The frame score is the mean over ground-truth objects.
  Extra predicted segments are not penalised.
* **UOIS metrics** (Xie et al., code of UnseenObjectClustering, re-implemented): segments are
  matched by the Hungarian algorithm maximising the pairwise overlap F-measure.
  ``overlap_P`` = Σ matched |P∩G| / Σ|P|, ``overlap_R`` = Σ matched |P∩G| / Σ|G|, ``overlap_F``
  their harmonic mean (0 when both are 0). ``boundary_*`` is the same over boundary pixels (DAVIS
  ``seg2bmap``), a boundary pixel counting as matched when the other segment's boundary lies
  within a disk of radius ceil(0.003 × image diagonal) pixels. ``F75`` is the share of
  ground-truth objects whose matched overlap F-measure is ≥ 0.75.

Edge cases: a frame without ground-truth objects is not scored (all metrics NaN, ``n_gt`` = 0;
aggregation skips it). A frame with objects but no prediction scores P = R = IoU = 0 and, as
in the UOIS code, overlap/boundary precision 1, recall 0, F 0, F75 0.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage
from scipy.optimize import linear_sum_assignment

PAPER_KEYS = ("P", "R", "IoU")
OVERLAP_KEYS = ("overlap_P", "overlap_R", "overlap_F", "F75")
BOUNDARY_KEYS = ("boundary_P", "boundary_R", "boundary_F")
METRIC_KEYS = PAPER_KEYS + OVERLAP_KEYS + BOUNDARY_KEYS
F75_THRESHOLD = 0.75
BOUNDARY_TOLERANCE = 0.003  # fraction of the image diagonal (UOIS/DAVIS default)


def boundary_radius(height: int, width: int, tolerance: float = BOUNDARY_TOLERANCE) -> int:
    """Radius (pixels) of the boundary-matching disk: ceil(tolerance × image diagonal)."""
    return int(math.ceil(tolerance * math.hypot(height, width)))


def _safe_div(a: float, b: float) -> float:
    return float(a) / float(b) if b > 0 else 0.0


def _harmonic(p: float, r: float) -> float:
    return 2 * p * r / (p + r) if p + r > 0 else 0.0


def unique_inverse(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(labels, return_inverse=True)`` (inverse flat), by a lookup table for small
    non-negative ids (instance maps), which is ~10× faster than sorting."""
    x = np.asarray(labels).ravel()
    if x.size and np.issubdtype(x.dtype, np.integer) and x.min() >= 0 and x.max() < (1 << 22):
        ids = np.flatnonzero(np.bincount(x))
        lut = np.zeros(int(ids[-1]) + 1, np.int64)
        lut[ids] = np.arange(len(ids))
        return ids.astype(x.dtype), lut[x]
    ids, inv = np.unique(x, return_inverse=True)
    return ids, inv.ravel()


def contingency(pred: np.ndarray, gt: np.ndarray):
    """Overlap counts of 1-D label arrays (0 = none).

    Returns (gt_ids, pred_ids, inter[n_gt, n_pred], gt_size[n_gt], pred_size[n_pred]) where sizes
    count all elements of a segment (the caller restricts to the scored foreground first).
    """
    gt_ids, g = unique_inverse(gt)
    pred_ids, p = unique_inverse(pred)
    table = np.bincount(g * len(pred_ids) + p, minlength=len(gt_ids) * len(pred_ids))
    table = table.reshape(len(gt_ids), len(pred_ids))
    gk, pk = gt_ids != 0, pred_ids != 0
    return gt_ids[gk], pred_ids[pk], table[np.ix_(gk, pk)], table[gk].sum(1), table[:, pk].sum(0)


def _empty(n_gt: int, n_pred: int) -> dict:
    out = {k: float("nan") for k in METRIC_KEYS}
    out.update(n_gt=n_gt, n_pred=n_pred, n_matched=0)
    return out


def segment_metrics(pred: np.ndarray, gt: np.ndarray, return_matches: bool = False) -> dict:
    """Paper and UOIS overlap metrics of label arrays of any shape (pixels or 3-D points).

    Elements with ``gt == 0`` are not scored. Boundary keys are NaN here (see :func:`frame_metrics`).
    With ``return_matches``, adds ``matches``: {gt id: pred id} of the paper's IoU matching, and
    ``uois_matches``: the F-measure matching as [(gt id, pred id)].
    """
    pred = np.asarray(pred).ravel()
    gt = np.asarray(gt).ravel()
    if pred.shape != gt.shape:
        raise ValueError(f"prediction has {pred.size} elements, ground truth {gt.size}")
    fg = gt != 0
    gt_ids, pred_ids, inter, gt_size, pred_size = contingency(pred[fg], gt[fg])
    n_gt, n_pred = len(gt_ids), len(pred_ids)
    out = _empty(n_gt, n_pred)
    if return_matches:
        out.update(matches={}, uois_matches=[])
    if n_gt == 0:
        return out
    if n_pred == 0:
        out.update({k: 0.0 for k in PAPER_KEYS + OVERLAP_KEYS}, overlap_P=1.0)
        return out
    inter = inter.astype(np.float64)
    union = gt_size[:, None] + pred_size[None, :] - inter
    iou = inter / union
    rows, cols = linear_sum_assignment(1.0 - iou)
    keep = inter[rows, cols] > 0  # a zero-overlap Hungarian pair counts as unmatched
    rows, cols = rows[keep], cols[keep]
    p = np.zeros(n_gt)
    r = np.zeros(n_gt)
    j = np.zeros(n_gt)
    p[rows] = inter[rows, cols] / pred_size[cols]
    r[rows] = inter[rows, cols] / gt_size[rows]
    j[rows] = iou[rows, cols]
    out.update(P=float(p.mean()), R=float(r.mean()), IoU=float(j.mean()), n_matched=int(len(rows)))

    f = 2 * inter / (gt_size[:, None] + pred_size[None, :])
    frows, fcols = linear_sum_assignment(1.0 - f)
    tp = inter[frows, fcols].sum()
    op, orr = _safe_div(tp, pred_size.sum()), _safe_div(tp, gt_size.sum())
    out.update(overlap_P=op, overlap_R=orr, overlap_F=_harmonic(op, orr),
               F75=float(np.sum(f[frows, fcols] >= F75_THRESHOLD)) / n_gt)
    if return_matches:
        out["matches"] = {int(gt_ids[a]): int(pred_ids[b]) for a, b in zip(rows, cols)}
        out["uois_matches"] = [(int(gt_ids[a]), int(pred_ids[b])) for a, b in zip(frows, fcols)]
    return out


def boundary_map(mask: np.ndarray) -> np.ndarray:
    """Boundary pixels of a binary mask, as DAVIS ``seg2bmap`` (pixels where the mask changes
    towards the east, south or south-east neighbour; the last row/column compare along the edge)."""
    m = np.asarray(mask, dtype=bool)
    e = np.zeros_like(m)
    s = np.zeros_like(m)
    se = np.zeros_like(m)
    e[:, :-1] = m[:, 1:]
    s[:-1, :] = m[1:, :]
    se[:-1, :-1] = m[1:, 1:]
    b = (m ^ e) | (m ^ s) | (m ^ se)
    b[-1, :] = m[-1, :] ^ e[-1, :]
    b[:, -1] = m[:, -1] ^ s[:, -1]
    b[-1, -1] = False
    return b


def disk(radius: int) -> np.ndarray:
    """uint8 structuring element: pixels with x² + y² ≤ radius² (skimage ``disk``)."""
    y, x = np.ogrid[-radius:radius + 1, -radius:radius + 1]
    return (x * x + y * y <= radius * radius).astype(np.uint8)


def _crop(slices: list[tuple[slice, slice]], pad: int, shape: tuple[int, int]) -> tuple[slice, slice]:
    """Union of bounding boxes, grown by ``pad`` and clipped to the image."""
    y0 = max(min(s[0].start for s in slices) - pad, 0)
    y1 = min(max(s[0].stop for s in slices) + pad, shape[0])
    x0 = max(min(s[1].start for s in slices) - pad, 0)
    x1 = min(max(s[1].stop for s in slices) + pad, shape[1])
    return slice(y0, y1), slice(x0, x1)


def _sequential(labels: np.ndarray) -> tuple[np.ndarray, dict[int, int], list]:
    """Relabel non-zero ids to 1..n: (sequential map, {id: sequential id}, bounding boxes by n − 1)."""
    ids, inv = unique_inverse(labels)
    offset = 1 if ids[0] != 0 else 0
    seq = inv.reshape(labels.shape) + offset
    pos = {int(v): i + offset for i, v in enumerate(ids) if v != 0}
    return seq, pos, ndimage.find_objects(seq)


def _boundary_scores(pred: np.ndarray, gt: np.ndarray, pairs: list[tuple[int, int]], radius: int) -> tuple[float, float]:
    """UOIS boundary precision and recall of the matched (gt id, pred id) pairs."""
    import cv2

    kernel = disk(radius)
    pad = radius + 2  # boundary pixels lie at most one pixel outside a mask's box
    gt_seq, gt_pos, gt_box = _sequential(gt)
    pr_seq, pr_pos, pr_box = _sequential(pred)

    def bsum(seq, boxes):
        return sum(int(boundary_map(seq[_crop([b], pad, seq.shape)] == i).sum()) for i, b in enumerate(boxes, 1))

    gt_den, pr_den = bsum(gt_seq, gt_box), bsum(pr_seq, pr_box)
    p_tp = r_tp = 0
    for g, p in pairs:
        gi, pi = gt_pos[g], pr_pos[p]
        sl = _crop([gt_box[gi - 1], pr_box[pi - 1]], pad, gt.shape)
        gb = boundary_map(gt_seq[sl] == gi)
        pb = boundary_map(pr_seq[sl] == pi)
        p_tp += int(np.count_nonzero(pb & cv2.dilate(gb.view(np.uint8), kernel).astype(bool)))
        r_tp += int(np.count_nonzero(gb & cv2.dilate(pb.view(np.uint8), kernel).astype(bool)))
    return _safe_div(p_tp, pr_den), _safe_div(r_tp, gt_den)


def frame_metrics(pred: np.ndarray, gt: np.ndarray, return_matches: bool = False,
                  tolerance: float = BOUNDARY_TOLERANCE) -> dict:
    """All metrics of one frame: ``pred`` and ``gt`` are H×W integer instance maps (0 = none).

    Scored over ``gt > 0`` only. Returns {metric: float, n_gt, n_pred, n_matched} (see the module
    docstring for definitions and edge cases).
    """
    pred = np.asarray(pred)
    gt = np.asarray(gt)
    if pred.shape != gt.shape or pred.ndim != 2:
        raise ValueError(f"prediction {pred.shape} and ground truth {gt.shape} must be the same H×W shape")
    pred = np.where(gt != 0, pred, 0)
    out = segment_metrics(pred, gt, return_matches=True)
    if out["n_gt"] == 0:
        pass
    elif out["n_pred"] == 0:
        out.update(boundary_P=1.0, boundary_R=0.0, boundary_F=0.0)
    else:
        bp, br = _boundary_scores(pred, gt, out["uois_matches"], boundary_radius(*gt.shape, tolerance))
        out.update(boundary_P=bp, boundary_R=br, boundary_F=_harmonic(bp, br))
    if not return_matches:
        del out["matches"], out["uois_matches"]
    return out
