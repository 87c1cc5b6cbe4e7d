"""Baseline B, ``uois-sim``: UOIS-Net-3D (Xie et al., T-RO 2021) in plain torch, trained with ground truth
on synthetic scenes of other objects (``train_data``, see ``baselines/sim_data.py``). RICE is not built.

* **Depth Seeding Network (DSN)**: the DeepLabV3+ of ``method/network.py`` on the organised point map
  (camera-frame XYZ, m; each frame's valid-point mean subtracted, divided by ``xyz_scale_m``) predicts
  a foreground logit and, per pixel, the 3-D offset (m) from the pixel's point to the centre of its
  object (the mean of the object's visible points in that frame). Loss: BCE on foreground plus
  ``offset_weight`` × smooth L1 on the offsets of object pixels (UOIS's separation loss is left out).
* **Centre voting**: the points of the given foreground mask vote point + offset; Gaussian mean-shift
  (bandwidth ``sigma_m``, farthest-point seeds) finds the modes, modes closer than ``merge_m`` merge,
  every vote joins its nearest mode. Clusters are split into connected components and small ones
  absorbed (``method/meanshift.py``), as UOIS's morphological clean-up.
* **Region Refinement Network (RRN)**: each initial mask's padded box is cropped from the RGB image,
  resized to ``rrn_size`` and, with the mask as a fourth channel, refined by a small U-Net. Trained
  on ground-truth masks perturbed as in UOIS (translation, dilation or erosion, added or cut
  ellipses). Refined masks are pasted largest first (smaller ones on top), restricted to the given
  foreground mask.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from selfseg.baselines.semantic_instances import finished, save_final, train_loop
from selfseg.baselines.sim_data import GTFrames, SimSchedule, SimTrainedMethod
from selfseg.dataset import Video
from selfseg.method.features import foreground_box
from selfseg.method.meanshift import absorb_small, split_components
from selfseg.method.network import RGB_MEAN, RGB_STD, EmbeddingNet, NetConfig
from selfseg.method.train import WEIGHTS, begin_training
from selfseg.raycast import xyz_map

# Settings read only at test time: changing them reuses the trained networks.
TEST_TIME_FIELDS = ("sigma_m", "n_seeds", "max_points", "meanshift_iters", "merge_m", "min_instance_px",
                    "rrn_threshold")


@dataclass
class UoisConfig:
    train_data: str = ""  # dataset folder generated with an object pool disjoint from the test data
    frame_stride: int = 3  # every n-th frame of every training video
    xyz_scale_m: float = 0.1
    dsn_net: NetConfig = field(default_factory=lambda: NetConfig.preset("fast", embed_dim=4))
    dsn_train: SimSchedule = field(default_factory=SimSchedule)
    offset_weight: float = 10.0
    rrn_width: int = 16  # channels of the RRN's first stage (× 1, 2, 4)
    rrn_size: int = 64  # crops are resized to rrn_size × rrn_size pixels
    rrn_pad: float = 0.25  # crop = mask box grown by this × its longer side
    rrn_train: SimSchedule = field(default_factory=lambda: SimSchedule(batch_size=16))
    # centre voting (test time)
    sigma_m: float = 0.02
    n_seeds: int = 50
    max_points: int = 3000  # votes subsampled to at most this many for the mean-shift
    meanshift_iters: int = 10
    merge_m: float = 0.03
    min_instance_px: int = 50  # smaller clusters are absorbed by a neighbour or dropped
    rrn_threshold: float = 0.5

    def __post_init__(self):
        if self.dsn_net.embed_dim != 4:
            raise ValueError(f"dsn_net.embed_dim must be 4 (foreground logit + 3-D offset), "
                             f"got {self.dsn_net.embed_dim}")
        if min(self.xyz_scale_m, self.sigma_m, self.merge_m) <= 0 or self.offset_weight < 0:
            raise ValueError("xyz_scale_m, sigma_m and merge_m must be > 0 and offset_weight ≥ 0")
        if min(self.frame_stride, self.n_seeds, self.max_points, self.meanshift_iters, self.rrn_width) < 1:
            raise ValueError("frame_stride, n_seeds, max_points, meanshift_iters and rrn_width must be ≥ 1")
        if self.rrn_size < 16 or self.rrn_size % 8 or self.rrn_pad < 0:
            raise ValueError(f"rrn_size must be a multiple of 8, ≥ 16, and rrn_pad ≥ 0; "
                             f"got {self.rrn_size}, {self.rrn_pad}")


# ---- DSN ------------------------------------------------------------------------------------------
def dsn_input(xyz: np.ndarray, scale_m: float) -> np.ndarray:
    """Organised point map H×W×3 (m, zeros = no depth) → 3×H×W float32, valid-mean subtracted, / ``scale_m``."""
    valid = xyz[..., 2] > 0
    mean = xyz[valid].mean(0) if valid.any() else np.zeros(3, np.float32)
    return np.where(valid[..., None], (xyz - mean) / scale_m, 0).transpose(2, 0, 1).astype(np.float32)


def dsn_forward(net: EmbeddingNet, x: torch.Tensor, scale_m: float) -> tuple[torch.Tensor, torch.Tensor]:
    """→ foreground logits B×H×W and offsets B×3×H×W (m)."""
    out = F.interpolate(net.forward_stride4(x), size=x.shape[2:], mode="bilinear", align_corners=False)
    return out[:, 0], out[:, 1:] * scale_m


def centre_targets(xyz: np.ndarray, inst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the offset (m, H×W×3) from its point to the mean of its instance's visible points, and
    the mask of object pixels with depth where that offset is defined."""
    valid = (inst > 0) & (xyz[..., 2] > 0)
    off = np.zeros_like(xyz)
    for k in np.unique(inst[valid]):
        m = valid & (inst == k)
        off[m] = xyz[m].mean(0) - xyz[m]
    return off, valid


def dsn_loss(net: EmbeddingNet, cfg: UoisConfig, frames: list[tuple[np.ndarray, ...]]) -> torch.Tensor:
    x = torch.from_numpy(np.stack([dsn_input(f[2], cfg.xyz_scale_m) for f in frames]))
    fg_logit, off = dsn_forward(net, x, cfg.xyz_scale_m)
    tg = [centre_targets(f[2], f[3]) for f in frames]
    target = torch.from_numpy(np.stack([t[0] for t in tg])).permute(0, 3, 1, 2)
    obj = torch.from_numpy(np.stack([t[1] for t in tg]))
    fg = torch.from_numpy(np.stack([f[3] > 0 for f in frames])).float()
    loss = F.binary_cross_entropy_with_logits(fg_logit, fg)
    if obj.any():
        err = (off - target).permute(0, 2, 3, 1)[obj] / cfg.xyz_scale_m
        loss = loss + cfg.offset_weight * F.smooth_l1_loss(err, torch.zeros_like(err), beta=0.1)
    return loss


def cluster_votes(votes: np.ndarray, sigma_m: float, n_seeds: int, iters: int, merge_m: float, max_points: int,
                  seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian mean-shift of N×3 votes (m) → (labels (N,) in 0..K−1, centres K×3).

    Seeds: farthest-point sampling of (at most ``max_points`` randomly kept) votes; each seed climbs
    ``iters`` mean-shift steps over the kept votes; converged seeds are visited densest first and
    start a new centre unless one lies within ``merge_m``; every vote joins its nearest centre.
    """
    v = torch.from_numpy(np.asarray(votes, np.float64))
    pts = v
    if len(v) > max_points:
        pts = v[torch.from_numpy(np.random.default_rng(seed).choice(len(v), max_points, replace=False))]
    chosen = [0]
    d = ((pts - pts[0]) ** 2).sum(1)
    for _ in range(min(n_seeds, len(pts)) - 1):
        chosen.append(int(torch.argmax(d)))
        d = torch.minimum(d, ((pts - pts[chosen[-1]]) ** 2).sum(1))
    s = pts[chosen]
    for _ in range(iters):
        w = torch.exp(-torch.cdist(s, pts) ** 2 / (2 * sigma_m ** 2))
        s = (w @ pts) / w.sum(1, keepdim=True).clamp(min=1e-300)
    density = torch.exp(-torch.cdist(s, pts) ** 2 / (2 * sigma_m ** 2)).sum(1)
    centres: list[torch.Tensor] = []
    for i in torch.argsort(density, descending=True, stable=True).tolist():
        if all(torch.linalg.norm(s[i] - c) >= merge_m for c in centres):
            centres.append(s[i])
    c = torch.stack(centres)
    return torch.argmin(torch.cdist(v, c), 1).numpy(), c.numpy()


# ---- RRN ------------------------------------------------------------------------------------------
def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
                         nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class RefineNet(nn.Module):
    """RRN: B×4×S×S (normalised RGB + initial mask) → B×S×S mask logits; a 3-level U-Net."""

    def __init__(self, width: int):
        super().__init__()
        w = width
        self.enc = nn.ModuleList([_block(4, w), _block(w, 2 * w), _block(2 * w, 4 * w)])
        self.mid = _block(4 * w, 4 * w)
        self.dec = nn.ModuleList([_block(8 * w, 2 * w), _block(4 * w, w), _block(2 * w, w)])
        self.out = nn.Conv2d(w, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        for enc in self.enc:
            x = enc(x)
            skips.append(x)
            x = F.max_pool2d(x, 2)
        x = self.mid(x)
        for dec, skip in zip(self.dec, reversed(skips)):
            x = dec(torch.cat([F.interpolate(x, size=skip.shape[2:], mode="bilinear", align_corners=False), skip], 1))
        return self.out(x)[:, 0]


def rrn_input(rgb: np.ndarray, mask: np.ndarray, box: tuple[int, int, int, int], size: int) -> np.ndarray:
    """RGB uint8 + bool mask, cropped to ``box`` and resized to size × size → 4×size×size float32."""
    y0, y1, x0, x1 = box
    img = cv2.resize(rgb[y0:y1, x0:x1].astype(np.float32) / 255.0, (size, size), interpolation=cv2.INTER_LINEAR)
    img = (img - np.array(RGB_MEAN, np.float32)) / np.array(RGB_STD, np.float32)
    m = cv2.resize(mask[y0:y1, x0:x1].astype(np.float32), (size, size), interpolation=cv2.INTER_NEAREST)
    return np.concatenate([img.transpose(2, 0, 1), m[None]], 0).astype(np.float32)


def perturb_mask(mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A ground-truth mask damaged as UOIS trains its RRN: shifted by up to 10% of its box, dilated or
    eroded, and an ellipse added or cut at its border."""
    ys, xs = np.nonzero(mask)
    size = max(ys.max() - ys.min() + 1, xs.max() - xs.min() + 1)
    m = mask.astype(np.uint8)
    dy, dx = (rng.uniform(-0.1, 0.1, 2) * size).round().astype(int)
    m = np.roll(m, (dy, dx), (0, 1))
    k = int(rng.integers(1, max(2, size // 10) + 1))
    kernel = np.ones((k, k), np.uint8)
    m = cv2.dilate(m, kernel) if rng.random() < 0.5 else cv2.erode(m, kernel)
    i = int(rng.integers(len(ys)))
    axes = tuple(int(a) for a in np.maximum(1, rng.uniform(0.1, 0.3, 2) * size))
    cv2.ellipse(m, (int(xs[i]), int(ys[i])), axes, float(rng.uniform(0, 180)), 0, 360, int(rng.random() < 0.5), -1)
    return m.astype(bool) if m.any() else mask.copy()


def rrn_batch(frames: GTFrames, cfg: UoisConfig, step: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Training crops of step ``step`` (pure in (seed, step)): perturbed masks in, ground-truth masks as targets."""
    rng = np.random.default_rng([cfg.rrn_train.seed, step, 1])
    xs, ts = [], []
    while len(xs) < cfg.rrn_train.batch_size:
        rgb, _, _, inst = frames[int(rng.integers(len(frames)))]
        ids, counts = np.unique(inst[inst > 0], return_counts=True)
        ids = ids[counts >= cfg.min_instance_px]
        if not len(ids):
            continue
        gt = inst == ids[int(rng.integers(len(ids)))]
        bad = perturb_mask(gt, rng)
        box = foreground_box(bad, cfg.rrn_pad)
        xs.append(rrn_input(rgb, bad, box, cfg.rrn_size))
        y0, y1, x0, x1 = box
        ts.append(cv2.resize(gt[y0:y1, x0:x1].astype(np.float32), (cfg.rrn_size,) * 2, interpolation=cv2.INTER_NEAREST))
    return torch.from_numpy(np.stack(xs)), torch.from_numpy(np.stack(ts))


def rrn_loss(rrn: RefineNet, frames: GTFrames, cfg: UoisConfig, step: int) -> torch.Tensor:
    x, target = rrn_batch(frames, cfg, step)
    return F.binary_cross_entropy_with_logits(rrn(x), target)


@torch.inference_mode()
def refine(rrn: RefineNet, cfg: UoisConfig, rgb: np.ndarray, initial: np.ndarray) -> np.ndarray:
    """Initial instance map (int H×W) → refined int32 map: each mask refined in its crop, pasted largest first."""
    ids, counts = np.unique(initial[initial > 0], return_counts=True)
    out = np.zeros(initial.shape, np.int32)
    if not len(ids):
        return out
    boxes = [foreground_box(initial == k, cfg.rrn_pad) for k in ids]
    x = torch.from_numpy(np.stack([rrn_input(rgb, initial == k, b, cfg.rrn_size) for k, b in zip(ids, boxes)]))
    probs = torch.sigmoid(rrn(x)).numpy()
    for j in np.argsort(-counts, kind="stable"):
        y0, y1, x0, x1 = boxes[j]
        p = cv2.resize(probs[j], (x1 - x0, y1 - y0), interpolation=cv2.INTER_LINEAR) >= cfg.rrn_threshold
        out[y0:y1, x0:x1][p] = j + 1
    return out


# ---- the method -----------------------------------------------------------------------------------
class UoisSim(SimTrainedMethod):
    """Baseline B: UOIS-Net-3D (DSN + RRN, no RICE) trained on a disjoint-object synthetic dataset."""

    name = "uois-sim"
    config_cls = UoisConfig
    test_time_fields = TEST_TIME_FIELDS

    def __init__(self, config=None, workdir: str | Path | None = None):
        super().__init__(config, workdir)
        self.dsn: EmbeddingNet | None = None
        self.rrn: RefineNet | None = None

    def fit(self, train_videos: list[Video]) -> None:
        cfg = self.config
        ds, base_key, out = self.open_training(train_videos)
        frames = None
        for name, make, sched, loss_fn in (
                ("dsn", lambda: EmbeddingNet(cfg.dsn_net), cfg.dsn_train, lambda step: dsn_loss(
                    self.dsn, cfg, frames.batch(cfg.dsn_train.seed, step, cfg.dsn_train.batch_size))),
                ("rrn", lambda: RefineNet(cfg.rrn_width), cfg.rrn_train,
                 lambda step: rrn_loss(self.rrn, frames, cfg, step))):
            key = {"phase": name, **base_key}
            phase_dir = out / name
            begin_training(sched)  # seeds the initial weights: build the network after it
            net = make()
            setattr(self, name, net)
            saved = finished(phase_dir / WEIGHTS, key)
            if saved is None:
                frames = frames if frames is not None else GTFrames(ds, cfg.frame_stride)
                opt = torch.optim.AdamW(net.parameters(), lr=sched.lr, weight_decay=sched.weight_decay)
                train_loop(phase_dir, key, {name: net}, opt, sched, loss_fn, {}, desc=f"{self.name} {name}")
                save_final(phase_dir / WEIGHTS, key, net=net.state_dict())
                saved = finished(phase_dir / WEIGHTS, key)
            net.load_state_dict(saved["net"])
            net.eval()

    def initial_masks(self, xyz: np.ndarray, fg_mask: np.ndarray) -> np.ndarray:
        """DSN + centre voting → int32 instance map inside ``fg_mask`` (pixels without depth stay 0)."""
        cfg = self.config
        with torch.inference_mode():
            _, off = dsn_forward(self.dsn, torch.from_numpy(dsn_input(xyz, cfg.xyz_scale_m))[None], cfg.xyz_scale_m)
        sel = fg_mask & (xyz[..., 2] > 0)
        inst = np.zeros(fg_mask.shape, np.int32)
        if not sel.any():
            return inst
        votes = xyz[sel] + off[0].permute(1, 2, 0).numpy()[sel]
        labels, _ = cluster_votes(votes, cfg.sigma_m, cfg.n_seeds, cfg.meanshift_iters, cfg.merge_m, cfg.max_points)
        inst[sel] = labels + 1
        return absorb_small(split_components(inst, 8), cfg.min_instance_px)

    def segment(self, video: Video, frame_id: int, fg_mask: np.ndarray) -> np.ndarray:
        fg = np.asarray(fg_mask, bool)
        initial = self.initial_masks(xyz_map(video.depth_m(frame_id), video.K(frame_id)), fg)
        return np.where(fg, refine(self.rrn, self.config, video.rgb(frame_id), initial), 0)
