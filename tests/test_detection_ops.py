"""Plain-torch detection operators against slow reference loops: RoIAlign, NMS, box coding, mask pasting."""
import math

import numpy as np
import torch

from selfseg.baselines.detection_ops import (box_iou, decode_boxes, encode_boxes, masks_to_boxes, nms, paste_masks,
                                            roi_align)


def bilinear_zero_padded(fmap: np.ndarray, x: float, y: float) -> float:
    """Value of a H×W map at continuous (x, y), pixel i centred at i + 0.5; corners outside read 0."""
    h, w = fmap.shape
    xi, yi = x - 0.5, y - 0.5
    x0, y0 = math.floor(xi), math.floor(yi)
    total = 0.0
    for yy, wy in ((y0, 1 - (yi - y0)), (y0 + 1, yi - y0)):
        for xx, wx in ((x0, 1 - (xi - x0)), (x0 + 1, xi - x0)):
            if 0 <= yy < h and 0 <= xx < w:
                total += wy * wx * fmap[yy, xx]
    return total


def slow_roi_align(feats: np.ndarray, roi: np.ndarray, p: int, scale: float, s: int) -> np.ndarray:
    b, x0, y0, x1, y1 = roi
    x0, y0, x1, y1 = x0 * scale, y0 * scale, x1 * scale, y1 * scale
    bw, bh = (x1 - x0) / p, (y1 - y0) / p
    out = np.zeros((feats.shape[1], p, p))
    for c in range(feats.shape[1]):
        for i in range(p):
            for j in range(p):
                vals = [bilinear_zero_padded(feats[int(b), c], x0 + (j + (q + 0.5) / s) * bw,
                                             y0 + (i + (r + 0.5) / s) * bh)
                        for r in range(s) for q in range(s)]
                out[c, i, j] = np.mean(vals)
    return out


def test_roi_align_matches_a_slow_bilinear_loop():
    rng = np.random.default_rng(0)
    feats = rng.normal(size=(2, 3, 9, 11))
    rois = np.array([[0, 4.0, 6.0, 30.0, 20.0], [1, -3.0, -2.0, 10.0, 12.5], [0, 20.0, 16.0, 44.0, 36.0],
                     [1, 5.3, 7.1, 5.9, 7.4]])  # inside, over the top-left edge, over the bottom-right edge, tiny
    got = roi_align(torch.from_numpy(feats), torch.from_numpy(rois), 5, 0.25, 2).numpy()
    for k, roi in enumerate(rois):
        np.testing.assert_allclose(got[k], slow_roi_align(feats, roi, 5, 0.25, 2), atol=1e-9)


def test_roi_align_of_a_linear_ramp_is_the_ramp_at_bin_centres():
    h, w = 16, 20
    ramp = torch.arange(w, dtype=torch.float64).add(0.5).expand(h, w)[None, None]  # value = x at pixel centres
    out = roi_align(ramp, torch.tensor([[0, 2.0, 3.0, 12.0, 13.0]], dtype=torch.float64), 5, 1.0, 2)[0, 0]
    np.testing.assert_allclose(out.numpy(), np.broadcast_to(2.0 + (np.arange(5) + 0.5) * 2.0, (5, 5)), atol=1e-12)


def brute_force_nms(boxes: np.ndarray, scores: np.ndarray, thr: float) -> list[int]:
    def iou(a, b):
        iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
        ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
        inter = iw * ih
        return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)

    kept = []
    for i in sorted(range(len(boxes)), key=lambda i: -scores[i]):
        if all(iou(boxes[i], boxes[k]) <= thr for k in kept):
            kept.append(i)
    return kept


def test_nms_matches_a_brute_force_loop():
    rng = np.random.default_rng(1)
    for trial in range(20):
        n = int(rng.integers(1, 60))
        xy = rng.uniform(0, 50, (n, 2))
        boxes = np.concatenate([xy, xy + rng.uniform(2, 25, (n, 2))], 1)
        scores = rng.permutation(n).astype(np.float64)  # distinct
        for thr in (0.3, 0.5, 0.7):
            got = nms(torch.from_numpy(boxes), torch.from_numpy(scores), thr).tolist()
            assert got == brute_force_nms(boxes, scores, thr), (trial, thr)
    assert nms(torch.zeros(0, 4), torch.zeros(0), 0.5).tolist() == []


def test_box_iou_known_values():
    a = torch.tensor([[0.0, 0, 10, 10]])
    b = torch.tensor([[0.0, 0, 10, 10], [5, 0, 15, 10], [20, 20, 30, 30]])
    np.testing.assert_allclose(box_iou(a, b).numpy(), [[1.0, 50 / 150, 0.0]])


def test_encode_decode_are_inverse():
    rng = np.random.default_rng(2)
    xy = rng.uniform(0, 100, (30, 2))
    ref = torch.from_numpy(np.concatenate([xy, xy + rng.uniform(3, 40, (30, 2))], 1))
    xy2 = rng.uniform(0, 100, (30, 2))
    tgt = torch.from_numpy(np.concatenate([xy2, xy2 + rng.uniform(3, 40, (30, 2))], 1))
    for w in ((1.0, 1.0, 1.0, 1.0), (10.0, 10.0, 5.0, 5.0)):
        torch.testing.assert_close(decode_boxes(ref, encode_boxes(ref, tgt, w), w), tgt)


def test_pasting_a_full_mask_fills_exactly_its_box_and_boxes_enclose_instances():
    inst = np.zeros((30, 40), np.int32)
    inst[5:12, 8:20] = 3
    inst[20:29, 30:33] = 7
    inst[0, 0] = 9  # one pixel: below min_px
    ids, boxes = masks_to_boxes(inst, min_px=2)
    assert ids.tolist() == [3, 7]
    np.testing.assert_array_equal(boxes, [[8, 5, 20, 12], [30, 20, 33, 29]])
    pasted = paste_masks(torch.ones(2, 28, 28), torch.from_numpy(boxes), 30, 40) >= 0.5
    np.testing.assert_array_equal(pasted[0].numpy(), inst == 3)
    np.testing.assert_array_equal(pasted[1].numpy(), inst == 7)
