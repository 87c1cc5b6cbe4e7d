"""Baseline F, `stego`: STEGO (Hamilton et al., ICLR 2022) on a ViT trained from scratch with DINO.

STEGO distils a frozen self-supervised ViT. No pretrained weights can be downloaded, so the backbone
is trained here, on the fold's unlabeled training frames, in three phases written from the papers'
descriptions (reference code may be read, never copied):

1. **DINO** (Caron et al. 2021): a small ViT (patch 8) and its projection head are the student; the
   teacher is their exponential moving average (momentum from ``teacher_momentum`` to 1, cosine).
   Multi-crop: two global and ``local_crops`` local crops of each training view; the teacher sees
   the global crops, the student all crops, and the loss is the cross-entropy between the teacher's
   centred, sharpened distribution softmax((t − c)/τ_t) and the student's softmax(s/τ_s) over every
   pair of different crops (:func:`dino_loss`); the centre c is an EMA of the teacher's batch mean
   (:func:`update_center`).
2. **STEGO's segmentation head** on the frozen teacher ViT's patch features f: a linear plus a
   two-layer 1×1-conv branch to ``embed_dim``-d codes c, trained with the feature-correspondence
   distillation loss (:func:`stego_corr_loss`): for two images with feature correlation
   F_ij = cos(f_i, f_j) (centred per row, "pointwise") and code correlation S_ij = cos(c_i, c_j),
   L = −Σ (F_ij − b) max(S_ij, 0), with three pairs: the image with itself (shift b_self), with one
   of its ``knn`` nearest neighbours in the backbone's global feature (b_knn), and with a random
   image (b_rand, the negative). Shifts are STEGO's COCO-Stuff values (0.18, 0.12, 0.46).
3. **Clustering**: spherical k-means of the head's foreground codes over the training frames into K
   classes (no CRF).

Foreground-masked: the views are foreground crops of the training frames (their own depth
foreground, :mod:`selfseg.baselines.semantic_instances`), and only patch pairs whose patches are both
mostly foreground enter the correlation loss and clustering. At test time every class is split
into connected components (ours' post-processing), which is how a semantic method gets an instance
score.
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from selfseg.baselines.semantic_instances import (Schedule, SemanticConfig, SemanticMethodBase, UnlabeledFrames,
                                                  final_centroids, finished, result_key, save_final, train_loop,
                                                  training_key)
from selfseg.fileio import hash_json
from selfseg.method.features import foreground_box
from selfseg.method.network import RGB_MEAN, RGB_STD
from selfseg.method.train import WEIGHTS, _jitter, augment, begin_training

DINO_DIR = "dino"  # in the training run's folder: phase 1's (DINO) run; its WEIGHTS hold the teacher ViT


@dataclass
class ViTConfig:
    """A small vision transformer (DINO's ViT-S/8 is patch 8, dim 384, depth 12, 6 heads)."""

    patch_px: int = 8
    dim: int = 96
    depth: int = 4
    heads: int = 3
    mlp_ratio: float = 4.0
    pos_grid: int = 20  # learned position embeddings on a pos_grid² grid, interpolated to the input's grid

    def __post_init__(self):
        if min(self.patch_px, self.dim, self.depth, self.heads, self.pos_grid) < 1 or self.mlp_ratio <= 0:
            raise ValueError("patch_px, dim, depth, heads, pos_grid and mlp_ratio must be positive")
        if self.dim % self.heads:
            raise ValueError(f"dim ({self.dim}) must be a multiple of heads ({self.heads})")


class ViT(nn.Module):
    """forward(rgb: B×3×H×W in [0, 1]) → (CLS token B×C, patch features B×C×⌈H/p⌉×⌈W/p⌉); the input is
    padded (replicated edge) to a multiple of the patch size."""

    def __init__(self, cfg: ViTConfig):
        super().__init__()
        self.cfg = cfg
        self.embed = nn.Conv2d(3, cfg.dim, cfg.patch_px, cfg.patch_px)
        self.cls = nn.Parameter(torch.zeros(1, 1, cfg.dim))
        self.pos = nn.Parameter(torch.randn(1, cfg.dim, cfg.pos_grid, cfg.pos_grid) * 0.02)
        self.pos_cls = nn.Parameter(torch.zeros(1, 1, cfg.dim))
        self.blocks = nn.ModuleList([nn.TransformerEncoderLayer(
            cfg.dim, cfg.heads, int(cfg.dim * cfg.mlp_ratio), dropout=0.0, activation="gelu", batch_first=True,
            norm_first=True) for _ in range(cfg.depth)])
        self.norm = nn.LayerNorm(cfg.dim)
        self.register_buffer("mean", torch.tensor(RGB_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(RGB_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, rgb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        p = self.cfg.patch_px
        h, w = rgb.shape[2:]
        x = F.pad((rgb - self.mean) / self.std, (0, -w % p, 0, -h % p), mode="replicate")
        x = self.embed(x)
        gh, gw = x.shape[2:]
        x = x + F.interpolate(self.pos, size=(gh, gw), mode="bilinear", align_corners=False)
        tokens = torch.cat([(self.cls + self.pos_cls).expand(len(x), -1, -1), x.flatten(2).transpose(1, 2)], 1)
        for blk in self.blocks:
            tokens = blk(tokens)
        tokens = self.norm(tokens)
        return tokens[:, 0], tokens[:, 1:].transpose(1, 2).reshape(len(x), -1, gh, gw)


class DinoHead(nn.Module):
    """DINO's projection head: 3-layer MLP to a bottleneck, L2-normalised, then a weight-normalised
    linear layer to ``out_dim`` logits (norm_last_layer)."""

    def __init__(self, dim: int, out_dim: int, hidden: int = 256, bottleneck: int = 64):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, hidden), nn.GELU(),
                                 nn.Linear(hidden, bottleneck))
        self.last = nn.Parameter(torch.randn(out_dim, bottleneck) * 0.02)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.linear(F.normalize(self.mlp(x), dim=-1), F.normalize(self.last, dim=1))


@dataclass
class StegoHeadConfig:
    embed_dim: int = 70  # STEGO's code dimension

    def __post_init__(self):
        if self.embed_dim < 1:
            raise ValueError(f"embed_dim must be ≥ 1, got {self.embed_dim}")


class StegoHead(nn.Module):
    """STEGO's segmentation head: linear 1×1 conv + (1×1 conv, ReLU, 1×1 conv), summed."""

    def __init__(self, dim: int, code_dim: int):
        super().__init__()
        self.linear = nn.Conv2d(dim, code_dim, 1)
        self.nonlinear = nn.Sequential(nn.Conv2d(dim, dim, 1), nn.ReLU(), nn.Conv2d(dim, code_dim, 1))

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        return self.linear(f) + self.nonlinear(f)


class StegoNet(nn.Module):
    """Backbone + head for inference: forward(rgb B×3×H×W) → B×D×H×W unit codes (bilinear from patches)."""

    def __init__(self, vit: ViT, head: StegoHead, cfg: StegoHeadConfig):
        super().__init__()
        self.vit, self.head, self.cfg = vit, head, cfg

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        h, w = rgb.shape[2:]
        codes = self.head(self.vit(rgb)[1])
        p = self.vit.cfg.patch_px
        up = F.interpolate(codes, size=(codes.shape[2] * p, codes.shape[3] * p), mode="bilinear", align_corners=False)
        return F.normalize(up[:, :, :h, :w], dim=1)


@dataclass
class DinoConfig:
    """DINO self-distillation of the backbone: schedule, multi-crop and temperatures."""

    train: Schedule = field(default_factory=lambda: Schedule(steps=3000, batch_size=16, lr=5e-4, weight_decay=0.04))
    out_dim: int = 1024  # prototypes of the projection head (DINO: 65536)
    student_temp: float = 0.1
    teacher_temp: float = 0.04
    center_momentum: float = 0.9
    teacher_momentum: float = 0.996  # EMA momentum at step 0, cosine to 1 at the end
    global_px: int = 64  # global crops, square, pixels
    global_scale: tuple[float, ...] = (0.4, 1.0)  # area fraction of the view
    local_crops: int = 4
    local_px: int = 32
    local_scale: tuple[float, ...] = (0.1, 0.4)

    def __post_init__(self):
        if self.out_dim < 2 or self.local_crops < 0 or min(self.global_px, self.local_px) < 8:
            raise ValueError("out_dim must be ≥ 2, local_crops ≥ 0 and crop sizes ≥ 8 px")
        if not (self.student_temp > 0 and self.teacher_temp > 0):
            raise ValueError("temperatures must be > 0")
        if not (0 <= self.center_momentum < 1 and 0 <= self.teacher_momentum <= 1):
            raise ValueError("center_momentum must be in [0, 1) and teacher_momentum in [0, 1]")
        for name in ("global_scale", "local_scale"):
            s = getattr(self, name)
            if len(s) != 2 or not 0 < s[0] <= s[1] <= 1:
                raise ValueError(f"{name} must be (lo, hi) with 0 < lo ≤ hi ≤ 1, got {s}")


@dataclass
class StegoConfig(SemanticConfig):
    """The three phases of STEGO (plus the shared classes, clustering and instance settings)."""

    vit: ViTConfig = field(default_factory=ViTConfig)
    dino: DinoConfig = field(default_factory=DinoConfig)
    head: StegoHeadConfig = field(default_factory=StegoHeadConfig)
    train: Schedule = field(default_factory=lambda: Schedule(steps=2000, batch_size=8, lr=5e-4))  # the head's
    knn: int = 7  # positives are drawn from each frame's knn nearest frames (global backbone feature)
    shift_self: float = 0.18
    shift_knn: float = 0.12
    shift_rand: float = 0.46
    weight_self: float = 1.0
    weight_knn: float = 1.0
    weight_rand: float = 1.0
    min_patch_fg: float = 0.5  # a patch is foreground if at least this fraction of its pixels is

    def __post_init__(self):
        super().__post_init__()
        if self.knn < 1:
            raise ValueError(f"knn must be ≥ 1, got {self.knn}")
        if min(self.weight_self, self.weight_knn, self.weight_rand) < 0 or not 0 < self.min_patch_fg <= 1:
            raise ValueError("the loss weights must be ≥ 0 and min_patch_fg in (0, 1]")


def dino_loss(student: torch.Tensor, teacher: torch.Tensor, center: torch.Tensor, student_temp: float,
              teacher_temp: float) -> torch.Tensor:
    """DINO's loss. student: V×B×O logits of V crops (the G global crops first), teacher: G×B×O logits
    of the global crops, center: O. Mean over the pairs (g, v ≠ g) and the batch of
    −Σ_o softmax((t − c)/τ_t)_o · log softmax(s/τ_s)_o; the teacher side carries no gradient."""
    q = F.softmax((teacher - center) / teacher_temp, dim=-1).detach()
    logp = F.log_softmax(student / student_temp, dim=-1)
    ce = -torch.einsum("gbo,vbo->gvb", q, logp).mean(-1)  # G×V
    g, v = ce.shape
    return ce[~torch.eye(g, v, dtype=torch.bool, device=ce.device)].mean()


def update_center(center: torch.Tensor, teacher: torch.Tensor, momentum: float) -> torch.Tensor:
    """DINO's centre: EMA of the teacher logits' mean over crops and batch (teacher: G×B×O)."""
    return center * momentum + teacher.detach().reshape(-1, teacher.shape[-1]).mean(0) * (1 - momentum)


def stego_corr_loss(f1: torch.Tensor, f2: torch.Tensor, c1: torch.Tensor, c2: torch.Tensor, m1: torch.Tensor,
                    m2: torch.Tensor, shift: float) -> torch.Tensor:
    """STEGO's correlation loss between images 1 and 2 (batched pairs), over foreground patch pairs.

    f: B×C×h×w backbone features (no gradient), c: B×D×h×w codes, m: B×h×w bool foreground patches.
    F = cos(f1_hw, f2_ij), centred per row (minus its mean over the foreground ij, plus the mean of
    F over all foreground pairs: STEGO's "pointwise"); S = cos(c1_hw, c2_ij);
    loss = mean over foreground pairs of −(F − shift)·max(S, 0). No foreground pair → 0.
    """
    valid = (m1[:, :, :, None, None] & m2[:, None, None, :, :]).float()
    n = valid.sum()
    if n == 0:
        return c1.sum() * 0.0 + c2.sum() * 0.0
    with torch.no_grad():
        fd = torch.einsum("bchw,bcij->bhwij", F.normalize(f1, dim=1), F.normalize(f2, dim=1))
        old_mean = (fd * valid).sum() / n
        row = (fd * valid).sum((3, 4), keepdim=True) / valid.sum((3, 4), keepdim=True).clamp_min(1)
        fd = fd - row
        fd = fd - (fd * valid).sum() / n + old_mean
    cd = torch.einsum("bchw,bcij->bhwij", F.normalize(c1, dim=1), F.normalize(c2, dim=1))
    return (-(fd - shift) * cd.clamp(min=0) * valid).sum() / n


def patch_foreground(fg: torch.Tensor, patch: int, min_fraction: float) -> torch.Tensor:
    """B×H×W bool pixels → B×⌈H/p⌉×⌈W/p⌉ bool patches with ≥ ``min_fraction`` foreground (padding is background)."""
    h, w = fg.shape[1:]
    x = F.pad(fg.float()[:, None], (0, -w % patch, 0, -h % patch))
    return F.avg_pool2d(x, patch)[:, 0] >= min_fraction


def random_resized_crop(img: np.ndarray, out_px: int, scale: tuple[float, ...], rng: np.random.Generator
                        ) -> np.ndarray:
    """A crop of H×W×3 ``img`` covering an area fraction in ``scale`` (aspect ratio log-uniform in
    [3/4, 4/3]), resized to out_px × out_px."""
    h, w = img.shape[:2]
    area = rng.uniform(*scale) * h * w
    ratio = math.exp(rng.uniform(math.log(3 / 4), math.log(4 / 3)))
    ch = int(np.clip(round(math.sqrt(area / ratio)), 1, h))
    cw = int(np.clip(round(math.sqrt(area * ratio)), 1, w))
    y0, x0 = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
    crop = img[y0:y0 + ch, x0:x0 + cw]
    return cv2.resize(crop, (out_px, out_px), interpolation=cv2.INTER_AREA if ch > out_px else cv2.INTER_LINEAR)


def multi_crop(frames: UnlabeledFrames, idx: list[int], cfg: DinoConfig, rng: np.random.Generator
               ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """DINO's crops of frames ``idx``: (2×B×3×g×g global, L×B×3×l×l local or None), flipped and jittered."""
    plain, jitter = cfg.train.augment_config(jitter=False), cfg.train.augment_config()
    glob, loc = [[] for _ in range(2)], [[] for _ in range(cfg.local_crops)]
    for i in idx:
        img, _ = augment(*frames[i], plain, rng)
        hwc = np.ascontiguousarray(img.transpose(1, 2, 0))
        for out, px, scale in [(g, cfg.global_px, cfg.global_scale) for g in glob] + \
                              [(lc, cfg.local_px, cfg.local_scale) for lc in loc]:
            c = random_resized_crop(hwc, px, scale, rng)
            if cfg.train.flip and rng.random() < 0.5:
                c = c[:, ::-1]
            out.append(torch.from_numpy(_jitter(np.ascontiguousarray(c), jitter, rng).transpose(2, 0, 1).copy()))
    stack = lambda views: torch.stack([torch.stack(v) for v in views])  # noqa: E731
    return stack(glob), (stack(loc) if loc else None)


def train_dino(frames: UnlabeledFrames, cfg: StegoConfig, out_dir: Path, progress: bool = True) -> tuple[ViT, dict]:
    """Phase 1: DINO into ``out_dir`` (resumable) → (the teacher ViT, the phase's key)."""
    key = {"phase": "dino", "vit": result_key(cfg.vit), "dino": result_key(cfg.dino),
           "frames": len(frames), "background": result_key(cfg.background), "frame_stride": cfg.frame_stride}
    weights = out_dir / WEIGHTS
    saved = finished(weights, key)
    if saved is None:
        d = cfg.dino
        device = begin_training(d.train)
        student = nn.ModuleDict({"vit": ViT(cfg.vit), "head": DinoHead(cfg.vit.dim, d.out_dim)})
        student = d.train.layout(student.to(device))
        teacher = copy.deepcopy(student)
        for p in teacher.parameters():
            p.requires_grad_(False)
        opt = torch.optim.AdamW(student.parameters(), lr=d.train.lr, weight_decay=d.train.weight_decay)
        state = {"center": torch.zeros(d.out_dim, device=device)}

        def run(net: nn.ModuleDict, crops: torch.Tensor) -> torch.Tensor:  # V×B×3×s×s → V×B×O (float32)
            v, b = crops.shape[:2]
            with d.train.autocast(device):
                out = net["head"](net["vit"](d.train.layout(crops.flatten(0, 1).to(device)))[0])
            return out.float().view(v, b, -1)

        def step_loss(step: int) -> torch.Tensor:
            rng = np.random.default_rng([d.train.seed, step])
            idx = rng.choice(len(frames), d.train.batch_size, replace=len(frames) < d.train.batch_size)
            glob, loc = multi_crop(frames, [int(i) for i in idx], d, rng)
            with torch.no_grad():
                t = run(teacher, glob)
            s = run(student, glob) if loc is None else torch.cat([run(student, glob), run(student, loc)])
            loss = dino_loss(s, t, state["center"], d.student_temp, d.teacher_temp)
            state["center"] = update_center(state["center"], t, d.center_momentum)
            return loss

        def ema(step: int) -> None:
            m = 1 - (1 - d.teacher_momentum) * (math.cos(math.pi * (step + 1) / d.train.steps) + 1) / 2
            with torch.no_grad():
                for pt, ps in zip(teacher.parameters(), student.parameters()):
                    pt.mul_(m).add_(ps.detach(), alpha=1 - m)

        train_loop(out_dir, key, {"student": student, "teacher": teacher}, opt, d.train, step_loss, state,
                   after_step=ema, desc="train dino", progress=progress)
        save_final(weights, key, vit=teacher["vit"].state_dict())
        return teacher["vit"].eval(), key
    vit = ViT(cfg.vit)
    vit.load_state_dict(saved["vit"])
    return vit.eval(), key


@torch.no_grad()
def nearest_frames(vit: ViT, frames: UnlabeledFrames, sched: Schedule, k: int, min_patch_fg: float,
                   device: torch.device) -> torch.Tensor:
    """N×k indices of each frame's most similar other frames (cosine of the mean normalised foreground
    patch feature of its test-time view: foreground box resized to ``image_size``)."""
    feats = []
    for rgb, lab in frames:
        fg = lab >= 0
        box = foreground_box(fg, sched.fg_crop_margin) if sched.fg_crop else None
        y0, y1, x0, x1 = box if box is not None else (0, fg.shape[0], 0, fg.shape[1])
        s = sched.image_size / max(y1 - y0, x1 - x0)
        size = (max(1, round((x1 - x0) * s)), max(1, round((y1 - y0) * s)))
        img = cv2.resize(rgb[y0:y1, x0:x1].astype(np.float32) / 255.0, size, interpolation=cv2.INTER_AREA)
        m = cv2.resize(fg[y0:y1, x0:x1].astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
        f = F.normalize(vit(torch.from_numpy(img.transpose(2, 0, 1).copy())[None].to(device))[1], dim=1)[0]
        pm = patch_foreground(torch.from_numpy(m)[None], vit.cfg.patch_px, min_patch_fg)[0].to(device)
        feats.append(f[:, pm].mean(1) if pm.any() else f.flatten(1).mean(1))
    g = F.normalize(torch.stack(feats), dim=1)
    sim = g @ g.T
    sim.fill_diagonal_(-math.inf)
    return sim.topk(min(k, max(1, len(frames) - 1)), dim=1).indices.cpu()


def train_stego(frames: UnlabeledFrames, cfg: StegoConfig, out_dir: Path, progress: bool = True
                ) -> tuple[StegoNet, torch.Tensor]:
    """All three phases into ``out_dir`` (``dino/`` and the head; resumable) → (network, K centroids)."""
    out_dir = Path(out_dir)
    vit, dino_key = train_dino(frames, cfg, out_dir / DINO_DIR, progress)
    key = {"phase": "stego", "dino": hash_json(dino_key), "config": training_key(cfg)}
    weights = out_dir / WEIGHTS
    saved = finished(weights, key)
    if saved is not None:
        head = StegoHead(cfg.vit.dim, cfg.head.embed_dim)
        head.load_state_dict(saved["head"])
        return StegoNet(vit, head, cfg.head).eval(), saved["centroids"]
    sched = cfg.train
    device = begin_training(sched)
    vit = sched.layout(vit.to(device)).eval()
    for p in vit.parameters():
        p.requires_grad_(False)
    knn = nearest_frames(vit, frames, sched, cfg.knn, cfg.min_patch_fg, device)
    head = StegoHead(cfg.vit.dim, cfg.head.embed_dim).to(device)
    opt = torch.optim.AdamW(head.parameters(), lr=sched.lr, weight_decay=sched.weight_decay)
    aug = sched.augment_config()

    def views(idx: np.ndarray, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        pairs = [augment(*frames[int(i)], aug, rng) for i in idx]
        img = sched.layout(torch.from_numpy(np.stack([p[0] for p in pairs])).to(device))
        fg = torch.from_numpy(np.stack([p[1] for p in pairs]) >= 0)
        with torch.no_grad(), sched.autocast(device):
            f = vit(img)[1].float()
        return f, patch_foreground(fg, cfg.vit.patch_px, cfg.min_patch_fg).to(device)

    def step_loss(step: int) -> torch.Tensor:
        rng = np.random.default_rng([sched.seed, step])
        idx = rng.choice(len(frames), sched.batch_size, replace=len(frames) < sched.batch_size)
        near = knn[idx, rng.integers(0, knn.shape[1], len(idx))].numpy()
        rand = rng.integers(0, len(frames), len(idx))
        (f, m), (fk, mk), (fr, mr) = views(idx, rng), views(near, rng), views(rand, rng)
        with sched.autocast(device):
            c, ck, cr = (head(x).float() for x in (f, fk, fr))
        return (cfg.weight_self * stego_corr_loss(f, f, c, c, m, m, cfg.shift_self)
                + cfg.weight_knn * stego_corr_loss(f, fk, c, ck, m, mk, cfg.shift_knn)
                + cfg.weight_rand * stego_corr_loss(f, fr, c, cr, m, mr, cfg.shift_rand))

    train_loop(out_dir, key, {"head": head}, opt, sched, step_loss, {}, desc="train stego head", progress=progress)
    net = StegoNet(vit, head, cfg.head).eval()
    centroids = final_centroids(net, frames, sched, cfg, device)
    save_final(weights, key, head=head.state_dict(), centroids=centroids.cpu())
    return net, centroids


class Stego(SemanticMethodBase):
    """Baseline F: STEGO on a from-scratch DINO ViT (k-means classes) → connected components per class."""

    name = "stego"
    config_cls = StegoConfig

    def train_model(self, frames: UnlabeledFrames, out_dir: Path) -> tuple[StegoNet, torch.Tensor]:
        return train_stego(frames, self.config, out_dir)
