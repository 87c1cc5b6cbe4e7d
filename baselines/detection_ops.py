"""Detection operators in plain torch (torchvision's compiled ops do not load with the CPU build).

Boxes are (x0, y0, x1, y1) in continuous pixel coordinates: pixel (u, v) covers [u, u + 1) × [v, v + 1),
so its centre is at (u + 0.5, v + 0.5). Used by ``sdmaskrcnn-sim`` (``baselines/maskrcnn.py``).
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

# Deltas are clamped before exp so that a wild prediction cannot overflow (log(1000 / 16), as Detectron).
_MAX_LOG_SCALE = float(np.log(1000.0 / 16))


def box_area(boxes: torch.Tensor) -> torch.Tensor:
    return (boxes[:, 2] - boxes[:, 0]).clamp(min=0) * (boxes[:, 3] - boxes[:, 1]).clamp(min=0)


def box_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """IoU of every box of ``a`` (N×4) with every box of ``b`` (M×4) → N×M."""
    lt = torch.maximum(a[:, None, :2], b[None, :, :2])
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    union = box_area(a)[:, None] + box_area(b)[None, :] - inter
    return inter / union.clamp(min=1e-9)


def nms(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Greedy non-maximum suppression → indices of the kept boxes, highest score first.

    A box is dropped when its IoU with a kept, higher-scoring box exceeds ``iou_threshold``.
    """
    order = torch.argsort(scores, descending=True, stable=True)
    if len(order) == 0:
        return order
    iou = box_iou(boxes[order], boxes[order])
    suppressed = torch.zeros(len(order), dtype=torch.bool)
    keep = []
    for i in range(len(order)):
        if suppressed[i]:
            continue
        keep.append(i)
        suppressed |= iou[i] > iou_threshold
    return order[torch.tensor(keep, dtype=torch.long)]


def encode_boxes(ref: torch.Tensor, target: torch.Tensor, weights: tuple[float, ...]) -> torch.Tensor:
    """Regression targets (dx, dy, dw, dh) of ``target`` relative to ``ref`` (both N×4), scaled by ``weights``."""
    wr, hr = ref[:, 2] - ref[:, 0], ref[:, 3] - ref[:, 1]
    wt, ht = target[:, 2] - target[:, 0], target[:, 3] - target[:, 1]
    cx = (target[:, 0] + 0.5 * wt - ref[:, 0] - 0.5 * wr) / wr
    cy = (target[:, 1] + 0.5 * ht - ref[:, 1] - 0.5 * hr) / hr
    return torch.stack([weights[0] * cx, weights[1] * cy, weights[2] * torch.log(wt / wr),
                        weights[3] * torch.log(ht / hr)], 1)


def decode_boxes(ref: torch.Tensor, deltas: torch.Tensor, weights: tuple[float, ...]) -> torch.Tensor:
    """Inverse of :func:`encode_boxes`: apply N×4 ``deltas`` to N×4 ``ref`` boxes."""
    wr, hr = ref[:, 2] - ref[:, 0], ref[:, 3] - ref[:, 1]
    cx, cy = ref[:, 0] + 0.5 * wr, ref[:, 1] + 0.5 * hr
    dx, dy = deltas[:, 0] / weights[0], deltas[:, 1] / weights[1]
    dw = (deltas[:, 2] / weights[2]).clamp(max=_MAX_LOG_SCALE)
    dh = (deltas[:, 3] / weights[3]).clamp(max=_MAX_LOG_SCALE)
    pcx, pcy, pw, ph = cx + dx * wr, cy + dy * hr, wr * torch.exp(dw), hr * torch.exp(dh)
    return torch.stack([pcx - 0.5 * pw, pcy - 0.5 * ph, pcx + 0.5 * pw, pcy + 0.5 * ph], 1)


def clip_boxes(boxes: torch.Tensor, height: int, width: int) -> torch.Tensor:
    return torch.stack([boxes[:, 0].clamp(0, width), boxes[:, 1].clamp(0, height),
                        boxes[:, 2].clamp(0, width), boxes[:, 3].clamp(0, height)], 1)


def roi_align(features: torch.Tensor, rois: torch.Tensor, output_size: int, spatial_scale: float,
              sampling_ratio: int = 2) -> torch.Tensor:
    """RoIAlign (the "aligned" variant) through ``grid_sample``.

    features: B×C×H×W; rois: K×5 (batch index, x0, y0, x1, y1) in image pixels; a feature cell i covers
    image pixels [i / spatial_scale, (i + 1) / spatial_scale). Each of the output_size² bins averages
    sampling_ratio² bilinear samples taken at the centres of a regular sub-grid of the bin; samples
    outside the feature map read zeros. → K×C×output_size×output_size.
    """
    B, C, H, W = features.shape
    P, s = output_size, sampling_ratio
    out = features.new_zeros(len(rois), C, P, P)
    if len(rois) == 0:
        return out
    t = (torch.arange(P * s, dtype=features.dtype, device=features.device) + 0.5) / (P * s)  # in [0, 1]
    for b in range(B):
        idx = torch.nonzero(rois[:, 0] == b).flatten()
        if len(idx) == 0:
            continue
        r = rois[idx, 1:] * spatial_scale  # feature-map continuous coordinates
        xs = r[:, 0:1] + t[None] * (r[:, 2:3] - r[:, 0:1])  # k × Ps
        ys = r[:, 1:2] + t[None] * (r[:, 3:4] - r[:, 1:2])
        gx = (xs / W * 2 - 1)[:, None, :].expand(-1, P * s, -1)  # align_corners=False: x = 0 ↔ −1
        gy = (ys / H * 2 - 1)[:, :, None].expand(-1, -1, P * s)
        grid = torch.stack([gx, gy], -1).reshape(1, len(idx) * P * s, P * s, 2)
        sampled = F.grid_sample(features[b:b + 1], grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        sampled = sampled.reshape(C, len(idx), P * s, P * s).transpose(0, 1)
        out[idx] = F.avg_pool2d(sampled, s)
    return out


def paste_masks(masks: torch.Tensor, boxes: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """M×m×m mask probabilities defined over their boxes (M×4) → M×height×width, bilinearly resampled at
    the pixel centres inside each box (0 outside)."""
    if len(masks) == 0:
        return masks.new_zeros(0, height, width)
    u = torch.arange(width, dtype=masks.dtype) + 0.5
    v = torch.arange(height, dtype=masks.dtype) + 0.5
    bw = (boxes[:, 2] - boxes[:, 0]).clamp(min=1e-6)
    bh = (boxes[:, 3] - boxes[:, 1]).clamp(min=1e-6)
    gx = ((u[None] - boxes[:, 0:1]) / bw[:, None]) * 2 - 1  # M × W; the box spans [−1, 1]
    gy = ((v[None] - boxes[:, 1:2]) / bh[:, None]) * 2 - 1
    grid = torch.stack([gx[:, None, :].expand(-1, height, -1), gy[:, :, None].expand(-1, -1, width)], -1)
    return F.grid_sample(masks[:, None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[:, 0]


def masks_to_boxes(inst: np.ndarray, min_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Instance map (int H×W, 0 = none) → (ids (n,), boxes n×4 float32) of the instances with ≥ ``min_px``
    pixels; a box encloses its instance's pixels (x1 = last column + 1)."""
    ids, counts = np.unique(inst[inst > 0], return_counts=True)
    ids = ids[counts >= min_px]
    boxes = np.zeros((len(ids), 4), np.float32)
    for i, k in enumerate(ids):
        ys, xs = np.nonzero(inst == k)
        boxes[i] = xs.min(), ys.min(), xs.max() + 1, ys.max() + 1
    return ids, boxes
