"""Baseline D, ``sdmaskrcnn-sim``: SD Mask R-CNN (Danielczuk et al., ICRA 2019) in plain torch, trained
with ground truth on synthetic scenes of other objects (``train_data``, see ``baselines/sim_data.py``).

Depth only, as SD Mask R-CNN: the depth image (m) is triplicated into three channels, each frame's
median valid depth subtracted and divided by ``depth_scale_m``. Class-agnostic Mask R-CNN: the
ResNet encoder of ``method/network.py`` (stride 4, 8 and 16 stages) + an FPN (P2–P4), an RPN
with anchors of one size per level and three aspect ratios, RoIAlign (``grid_sample``), a 2-FC box
head (object vs background, class-agnostic box deltas) and a 4-conv + deconvolution mask head
(28×28). At test time detections above ``score_threshold`` survive NMS; their masks are pasted
highest score first (a pixel belongs to the first mask that claims it) and restricted to the
given foreground mask.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from selfseg.baselines.detection_ops import (box_iou, clip_boxes, decode_boxes, encode_boxes, masks_to_boxes, nms,
                                            paste_masks, roi_align)
from selfseg.baselines.semantic_instances import finished, save_final, train_loop
from selfseg.baselines.sim_data import GTFrames, SimSchedule, SimTrainedMethod
from selfseg.dataset import Video
from selfseg.method.network import ENCODER_BLOCKS, ResNetEncoder
from selfseg.method.train import WEIGHTS, begin_training

RPN_WEIGHTS = (1.0, 1.0, 1.0, 1.0)
BOX_WEIGHTS = (10.0, 10.0, 5.0, 5.0)
STRIDES = (4, 8, 16)  # P2, P3, P4
# Settings read only at test time: changing them reuses the trained network.
TEST_TIME_FIELDS = ("score_threshold", "detection_nms", "max_detections", "mask_threshold")


@dataclass
class MaskRCNNNetConfig:
    """Architecture; anchor sizes (pixels, one per FPN level P2–P4) suit objects of 10–100 px."""

    encoder: str = "resnet18"
    width: int = 32  # first ResNet stage; stages width × (1, 2, 4, 8)
    fpn_channels: int = 64
    anchor_sizes_px: tuple[int, ...] = (16, 32, 64)
    aspect_ratios: tuple[float, ...] = (0.5, 1.0, 2.0)
    box_fc: int = 256
    mask_channels: int = 64
    canonical_roi_px: float = 32.0  # a RoI of this size pools from P3; ×2 per level up or down

    def __post_init__(self):
        if self.encoder not in ENCODER_BLOCKS:
            raise ValueError(f"encoder {self.encoder!r} unknown; choose one of {sorted(ENCODER_BLOCKS)}")
        if len(self.anchor_sizes_px) != len(STRIDES):
            raise ValueError(f"anchor_sizes_px needs one size per level {STRIDES}, got {self.anchor_sizes_px}")


@dataclass
class SDMaskRCNNConfig:
    train_data: str = ""  # dataset folder generated with an object pool disjoint from the test data
    frame_stride: int = 3  # every n-th frame of every training video
    min_instance_px: int = 20  # smaller ground-truth instances are not training targets
    depth_scale_m: float = 0.1
    net: MaskRCNNNetConfig = field(default_factory=MaskRCNNNetConfig)
    train: SimSchedule = field(default_factory=SimSchedule)
    rpn_batch: int = 256  # anchors sampled per image, at most half positive
    roi_batch: int = 128  # RoIs sampled per image, at most a quarter positive
    pre_nms: int = 1000  # proposals per image before NMS (training; half at test time)
    post_nms: int = 200  # proposals kept per image after NMS (training; half at test time)
    rpn_nms: float = 0.7
    score_threshold: float = 0.5
    detection_nms: float = 0.5
    max_detections: int = 50
    mask_threshold: float = 0.5

    def __post_init__(self):
        if self.frame_stride < 1 or self.depth_scale_m <= 0:
            raise ValueError(f"frame_stride must be ≥ 1 and depth_scale_m > 0, got {self.frame_stride}, "
                             f"{self.depth_scale_m}")
        if not (0 <= self.score_threshold < 1 and 0 < self.mask_threshold < 1):
            raise ValueError("score_threshold must be in [0, 1) and mask_threshold in (0, 1)")


def depth_input(depth_m: np.ndarray, scale_m: float) -> np.ndarray:
    """Depth (m, H×W, 0 = none) → 3×H×W float32: median-centred, divided by ``scale_m``, triplicated;
    0 where missing."""
    valid = depth_m > 0
    d = np.where(valid, (depth_m - (np.median(depth_m[valid]) if valid.any() else 0.0)) / scale_m, 0.0)
    return np.repeat(d[None].astype(np.float32), 3, 0)


def anchors_for(height: int, width: int, cfg: MaskRCNNNetConfig) -> list[torch.Tensor]:
    """Anchors per level (level l: ceil(H/s)·ceil(W/s)·A × 4, cell-major), centred on each cell's centre."""
    out = []
    for stride, size in zip(STRIDES, cfg.anchor_sizes_px):
        ws = torch.tensor([size / np.sqrt(r) for r in cfg.aspect_ratios], dtype=torch.float32)
        hs = torch.tensor([size * np.sqrt(r) for r in cfg.aspect_ratios], dtype=torch.float32)
        fh, fw = -(-height // stride), -(-width // stride)
        cy, cx = torch.meshgrid((torch.arange(fh) + 0.5) * stride, (torch.arange(fw) + 0.5) * stride, indexing="ij")
        c = torch.stack([cx.flatten(), cy.flatten()], 1)[:, None]  # cells × 1 × 2
        half = torch.stack([ws, hs], 1)[None] / 2
        out.append(torch.cat([c - half, c + half], -1).reshape(-1, 4))
    return out


class MaskRCNN(nn.Module):
    """Backbone + FPN, RPN, box and mask heads; see the module docstring."""

    def __init__(self, cfg: MaskRCNNNetConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = ResNetEncoder(ENCODER_BLOCKS[cfg.encoder], cfg.width, output_stride=16)
        c = cfg.fpn_channels
        self.lateral = nn.ModuleList([nn.Conv2d(ch, c, 1) for ch in (cfg.width, cfg.width * 2, cfg.width * 8)])
        self.smooth = nn.ModuleList([nn.Conv2d(c, c, 3, padding=1) for _ in STRIDES])
        a = len(cfg.aspect_ratios)
        self.rpn_conv = nn.Conv2d(c, c, 3, padding=1)
        self.rpn_obj = nn.Conv2d(c, a, 1)
        self.rpn_box = nn.Conv2d(c, 4 * a, 1)
        self.box_head = nn.Sequential(nn.Flatten(), nn.Linear(c * 49, cfg.box_fc), nn.ReLU(inplace=True),
                                      nn.Linear(cfg.box_fc, cfg.box_fc), nn.ReLU(inplace=True))
        self.box_cls = nn.Linear(cfg.box_fc, 1)  # object logit (class-agnostic)
        self.box_reg = nn.Linear(cfg.box_fc, 4)
        m = cfg.mask_channels
        self.mask_head = MaskHead(c, m)
        for mod in (self.rpn_obj, self.rpn_box, self.box_cls, self.box_reg):
            nn.init.normal_(mod.weight, std=0.01 if mod is not self.box_reg else 0.001)
            nn.init.zeros_(mod.bias)

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """B×3×H×W input → FPN levels P2, P3, P4 (strides 4, 8, 16)."""
        e = self.encoder
        c2 = e.layer1(e.stem(x))
        c3 = e.layer2(c2)
        c4 = e.layer4(e.layer3(c3))
        p4 = self.lateral[2](c4)
        p3 = self.lateral[1](c3) + F.interpolate(p4, size=c3.shape[2:], mode="nearest")
        p2 = self.lateral[0](c2) + F.interpolate(p3, size=c2.shape[2:], mode="nearest")
        return [s(p) for s, p in zip(self.smooth, (p2, p3, p4))]

    def rpn(self, feats: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """→ objectness logits B×N and deltas B×N×4 over all anchors (order of :func:`anchors_for`)."""
        objs, deltas = [], []
        for p in feats:
            h = F.relu(self.rpn_conv(p))
            B = p.shape[0]
            objs.append(self.rpn_obj(h).permute(0, 2, 3, 1).reshape(B, -1))
            deltas.append(self.rpn_box(h).permute(0, 2, 3, 1).reshape(B, -1, 4))
        return torch.cat(objs, 1), torch.cat(deltas, 1)

    def pool(self, feats: list[torch.Tensor], rois: torch.Tensor, size: int) -> torch.Tensor:
        """RoIAlign each RoI (K×5) from the FPN level its size picks."""
        wh = torch.sqrt(((rois[:, 3] - rois[:, 1]) * (rois[:, 4] - rois[:, 2])).clamp(min=1e-6))
        lvl = (torch.floor(torch.log2(wh / self.cfg.canonical_roi_px) + 0.5) + 1).clamp(0, len(STRIDES) - 1).long()
        out = feats[0].new_zeros(len(rois), feats[0].shape[1], size, size)
        for i, stride in enumerate(STRIDES):
            sel = torch.nonzero(lvl == i).flatten()
            if len(sel):
                out[sel] = roi_align(feats[i], rois[sel], size, 1.0 / stride)
        return out


class MaskHead(nn.Module):
    """14×14 RoI features → 4 × (3×3 conv, ReLU) → 2× deconvolution → 28×28 mask logits."""

    def __init__(self, cin: int, channels: int):
        super().__init__()
        layers, c = [], cin
        for _ in range(4):
            layers += [nn.Conv2d(c, channels, 3, padding=1), nn.ReLU(inplace=True)]
            c = channels
        self.convs = nn.Sequential(*layers)
        self.up = nn.ConvTranspose2d(channels, channels, 2, 2)
        self.out = nn.Conv2d(channels, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(F.relu(self.up(self.convs(x))))[:, 0]


def _proposals(anchors: torch.Tensor, obj: torch.Tensor, deltas: torch.Tensor, hw: tuple[int, int],
               pre: int, post: int, thr: float) -> list[torch.Tensor]:
    out = []
    for b in range(obj.shape[0]):
        top = torch.topk(obj[b], min(pre, obj.shape[1])).indices
        boxes = clip_boxes(decode_boxes(anchors[top], deltas[b, top], RPN_WEIGHTS), *hw)
        ok = ((boxes[:, 2] - boxes[:, 0]) >= 1) & ((boxes[:, 3] - boxes[:, 1]) >= 1)
        boxes, scores = boxes[ok], obj[b, top][ok]
        out.append(boxes[nms(boxes, scores, thr)[:post]])
    return out


def _sample(labels: torch.Tensor, n: int, pos_fraction: float, gen: torch.Generator) -> torch.Tensor:
    """Indices of at most ``n`` labelled items (1 = positive, 0 = negative, −1 = ignore), at most
    ``pos_fraction`` of them positive."""
    pos, neg = torch.nonzero(labels == 1).flatten(), torch.nonzero(labels == 0).flatten()
    n_pos = min(len(pos), int(n * pos_fraction))
    n_neg = min(len(neg), n - n_pos)
    return torch.cat([pos[torch.randperm(len(pos), generator=gen)[:n_pos]],
                      neg[torch.randperm(len(neg), generator=gen)[:n_neg]]])


def detection_loss(model: MaskRCNN, cfg: SDMaskRCNNConfig, frames: list[tuple[np.ndarray, ...]],
                   gen: torch.Generator) -> torch.Tensor:
    """Mask R-CNN loss of a batch of (rgb, depth, xyz, inst) frames: RPN (BCE + smooth L1), box head
    (BCE + smooth L1 on positives), mask head (per-pixel BCE on 28×28 targets RoIAligned from the
    ground-truth instance)."""
    H, W = frames[0][1].shape
    x = torch.from_numpy(np.stack([depth_input(f[1], cfg.depth_scale_m) for f in frames]))
    feats = model.features(x)
    obj, deltas = model.rpn(feats)
    anchors = torch.cat(anchors_for(H, W, model.cfg))
    with torch.no_grad():
        props = _proposals(anchors, obj.detach(), deltas.detach(), (H, W), cfg.pre_nms, cfg.post_nms, cfg.rpn_nms)
    rpn_cls, rpn_reg, rois, roi_tgt, roi_lab, roi_masks = [], [], [], [], [], []
    for b, f in enumerate(frames):
        ids, gt = masks_to_boxes(f[3], cfg.min_instance_px)
        gt = torch.from_numpy(gt)
        lab = torch.zeros(len(anchors))
        if len(gt):
            iou = box_iou(anchors, gt)
            best, match = iou.max(1)
            lab[best < 0.7] = -1
            lab[best < 0.3] = 0
            lab[best >= 0.7] = 1
            lab[(iou == iou.max(0).values[None]).any(1) & (best > 0)] = 1  # each box's best anchors
        idx = _sample(lab, cfg.rpn_batch, 0.5, gen)
        rpn_cls.append(F.binary_cross_entropy_with_logits(obj[b, idx], lab[idx], reduction="sum") / max(len(idx), 1))
        pos = idx[lab[idx] == 1]
        if len(pos):
            t = encode_boxes(anchors[pos], gt[match[pos]], RPN_WEIGHTS)
            rpn_reg.append(F.smooth_l1_loss(deltas[b, pos], t, beta=1 / 9, reduction="sum") / max(len(idx), 1))
        cand = torch.cat([props[b], gt]) if len(gt) else props[b]
        rlab = torch.zeros(len(cand))
        rmatch = torch.zeros(len(cand), dtype=torch.long)
        if len(gt):
            best, rmatch = box_iou(cand, gt).max(1)
            rlab = (best >= 0.5).float()
        sel = _sample(rlab, cfg.roi_batch, 0.25, gen)
        rois.append(torch.cat([torch.full((len(sel), 1), float(b)), cand[sel]], 1))
        roi_lab.append(rlab[sel])
        masks = torch.zeros(len(sel), 28, 28, dtype=torch.bool)  # targets of the positive RoIs only
        if len(gt):
            roi_tgt.append(encode_boxes(cand[sel], gt[rmatch[sel]], BOX_WEIGHTS))
            p = torch.nonzero(rlab[sel] == 1).flatten()
            inst = torch.from_numpy(f[3])
            gt_masks = torch.stack([(inst == int(k)).float() for k in ids])[rmatch[sel[p]]]
            one = torch.cat([torch.arange(len(p), dtype=torch.float32)[:, None], cand[sel[p]]], 1)
            masks[p] = roi_align(gt_masks[:, None], one, 28, 1.0, 2)[:, 0] >= 0.5
        else:
            roi_tgt.append(torch.zeros(len(sel), 4))
        roi_masks.append(masks)
    rois, roi_lab, roi_tgt, roi_masks = torch.cat(rois), torch.cat(roi_lab), torch.cat(roi_tgt), torch.cat(roi_masks)
    h = model.box_head(model.pool(feats, rois, 7))
    loss = torch.stack(rpn_cls).mean() + (torch.stack(rpn_reg).sum() / len(frames) if rpn_reg else 0.0)
    loss = loss + F.binary_cross_entropy_with_logits(model.box_cls(h)[:, 0], roi_lab)
    pos = torch.nonzero(roi_lab == 1).flatten()
    if len(pos):
        loss = loss + F.smooth_l1_loss(model.box_reg(h)[pos], roi_tgt[pos], beta=1.0, reduction="sum") / len(rois)
        logits = model.mask_head(model.pool(feats, rois[pos], 14))
        loss = loss + F.binary_cross_entropy_with_logits(logits, roi_masks[pos].float())
    return loss


@torch.inference_mode()
def detect(model: MaskRCNN, cfg: SDMaskRCNNConfig, depth_m: np.ndarray
           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One frame → (boxes D×4, scores D, mask probabilities D×H×W), highest score first."""
    H, W = depth_m.shape
    feats = model.features(torch.from_numpy(depth_input(depth_m, cfg.depth_scale_m))[None])
    obj, deltas = model.rpn(feats)
    anchors = torch.cat(anchors_for(H, W, model.cfg))
    props = _proposals(anchors, obj, deltas, (H, W), cfg.pre_nms // 2, cfg.post_nms // 2, cfg.rpn_nms)[0]
    rois = torch.cat([torch.zeros(len(props), 1), props], 1)
    h = model.box_head(model.pool(feats, rois, 7))
    scores = torch.sigmoid(model.box_cls(h)[:, 0])
    boxes = clip_boxes(decode_boxes(props, model.box_reg(h), BOX_WEIGHTS), H, W)
    ok = (scores >= cfg.score_threshold) & ((boxes[:, 2] - boxes[:, 0]) >= 1) & ((boxes[:, 3] - boxes[:, 1]) >= 1)
    boxes, scores = boxes[ok], scores[ok]
    keep = nms(boxes, scores, cfg.detection_nms)[:cfg.max_detections]
    boxes, scores = boxes[keep], scores[keep]
    rois = torch.cat([torch.zeros(len(boxes), 1), boxes], 1)
    masks = torch.sigmoid(model.mask_head(model.pool(feats, rois, 14))) if len(boxes) else torch.zeros(0, 28, 28)
    return boxes, scores, paste_masks(masks, boxes, H, W)


def masks_to_instances(probs: torch.Tensor, threshold: float, fg_mask: np.ndarray) -> np.ndarray:
    """D×H×W mask probabilities (highest score first) → int32 instance map: each pixel takes the first mask
    over ``threshold``, restricted to ``fg_mask``; ids 1..D in that order."""
    inst = np.zeros(fg_mask.shape, np.int32)
    for k, p in enumerate(probs.numpy() >= threshold, start=1):
        inst[p & (inst == 0)] = k
    return np.where(fg_mask, inst, 0)


class SDMaskRCNNSim(SimTrainedMethod):
    """Baseline D: SD Mask R-CNN (depth-only Mask R-CNN) trained on a disjoint-object synthetic dataset."""

    name = "sdmaskrcnn-sim"
    config_cls = SDMaskRCNNConfig
    test_time_fields = TEST_TIME_FIELDS

    def __init__(self, config=None, workdir: str | Path | None = None):
        super().__init__(config, workdir)
        self.model: MaskRCNN | None = None

    def fit(self, train_videos: list[Video]) -> None:
        cfg = self.config
        ds, key, out = self.open_training(train_videos)
        begin_training(cfg.train)  # seeds the initial weights: build the network after it
        self.model = MaskRCNN(cfg.net)
        saved = finished(out / WEIGHTS, key)
        if saved is None:
            frames = GTFrames(ds, cfg.frame_stride)
            opt = torch.optim.AdamW(self.model.parameters(), lr=cfg.train.lr, weight_decay=cfg.train.weight_decay)

            def step_loss(step: int) -> torch.Tensor:
                gen = torch.Generator().manual_seed(cfg.train.seed * 1_000_003 + step)
                return detection_loss(self.model, cfg, frames.batch(cfg.train.seed, step, cfg.train.batch_size), gen)

            train_loop(out, key, {"model": self.model}, opt, cfg.train, step_loss, {}, desc=f"{self.name} train")
            save_final(out / WEIGHTS, key, model=self.model.state_dict())
            saved = finished(out / WEIGHTS, key)
        self.model.load_state_dict(saved["model"])
        self.model.eval()

    def segment(self, video: Video, frame_id: int, fg_mask: np.ndarray) -> np.ndarray:
        _, _, probs = detect(self.model, self.config, video.depth_m(frame_id))
        return masks_to_instances(probs, self.config.mask_threshold, np.asarray(fg_mask, bool))
