"""Baseline E, `picie`: PiCIE (Cho et al., CVPR 2021), trained from scratch on the fold's unlabeled videos.

Written from the paper's description. A ResNet encoder (:class:`selfseg.method.network.ResNetEncoder`)
with an FPN head gives unit per-pixel features z = f(x). Every training image gets two photometric
jitters P1, P2 and one geometric transform G (a random crop resized back, and a random horizontal
flip), giving the two views

    view 1: z1 = f(G(P1 x))    (transform the image, then segment)
    view 2: z2 = G(f(P2 x))    (segment, then transform the features)

which must agree (equivariance to G, invariance to P). Every ``cluster_every`` steps (an "epoch")
the foreground features of each view over all training frames are clustered by spherical k-means
into K centroids μ1, μ2. Pixels are labelled by their nearest centroid, y_v = argmax z_v·μ_v, and
the loss is the cluster classification with logits z·μ/τ (τ = 1: PiCIE's cosine classifier):

    L = w_within (CE(z1, μ1, y1) + CE(z2, μ2, y2)) + w_cross (CE(z1, μ2, y2) + CE(z2, μ1, y1)).

Differences from the reference: labels come from the current batch's features and the epoch's
centroids (PiCIE stores the labels of the clustering pass; both use the network of the epoch start
for the centroids), exact k-means on a pixel sample instead of faiss mini-batch k-means, no
class-balancing weights. Masked to the foreground: only foreground pixels (the training frames'
own depth foreground, see :mod:`selfseg.baselines.semantic_instances`) enter clustering and loss.

At test time the trained features of the foreground pixels are assigned to K centroids fitted on
the training frames, and every class is split into connected components (ours' post-processing):
that is how a semantic method gets an instance score.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from selfseg.baselines.semantic_instances import (Schedule, SemanticConfig, SemanticMethodBase, UnlabeledFrames,
                                                  final_centroids, finished, sample_pixels, save_final, spherical_kmeans,
                                                  train_loop, training_key)
from selfseg.config import from_dict, to_dict
from selfseg.method.network import ENCODER_BLOCKS, RGB_MEAN, RGB_STD, ResNetEncoder, _conv_bn_relu
from selfseg.method.train import WEIGHTS, SpeedSettings, _jitter, augment, begin_training


@dataclass
class PicieNetConfig:
    """ResNet encoder + FPN head; ``width`` = channels of the first ResNet stage (PiCIE: ResNet-18, 64, 128-d)."""

    encoder: str = "resnet18"
    width: int = 32
    fpn_channels: int = 64
    embed_dim: int = 32

    def __post_init__(self):
        if self.encoder not in ENCODER_BLOCKS:
            raise ValueError(f"encoder {self.encoder!r} unknown; choose one of {sorted(ENCODER_BLOCKS)}")
        if min(self.width, self.fpn_channels, self.embed_dim) < 1:
            raise ValueError("width, fpn_channels and embed_dim must be ≥ 1")


class PicieNet(nn.Module):
    """forward(rgb: B×3×H×W in [0, 1]) → B×D×H×W unit features (FPN output at stride 4, upsampled)."""

    def __init__(self, cfg: PicieNetConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = ResNetEncoder(ENCODER_BLOCKS[cfg.encoder], cfg.width, output_stride=16)
        chans = [cfg.width, cfg.width * 2, cfg.width * 4, cfg.width * 8]
        self.lateral = nn.ModuleList([nn.Conv2d(c, cfg.fpn_channels, 1) for c in chans])
        self.head = nn.Sequential(_conv_bn_relu(cfg.fpn_channels, cfg.fpn_channels),
                                  nn.Conv2d(cfg.fpn_channels, cfg.embed_dim, 1))
        self.register_buffer("mean", torch.tensor(RGB_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(RGB_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        e = self.encoder
        c1 = e.layer1(e.stem((rgb - self.mean) / self.std))
        c2 = e.layer2(c1)
        c3 = e.layer3(c2)
        c4 = e.layer4(c3)
        p = self.lateral[3](c4)
        for lat, c in zip(self.lateral[2::-1], (c3, c2, c1)):  # top-down: upsample and add the lateral
            p = lat(c) + F.interpolate(p, size=c.shape[2:], mode="bilinear", align_corners=False)
        z = F.interpolate(self.head(p), size=rgb.shape[2:], mode="bilinear", align_corners=False)
        return F.normalize(z, dim=1)


@dataclass
class PicieConfig(SemanticConfig):
    """PiCIE's network, schedule and losses (plus the shared classes, clustering and instance settings)."""

    net: PicieNetConfig = field(default_factory=PicieNetConfig)
    train: Schedule = field(default_factory=lambda: Schedule(steps=1000, batch_size=8, lr=1e-3))
    cluster_every: int = 100  # steps per epoch: the views' features are re-clustered at every epoch start
    tau: float = 1.0  # logits z·μ/τ; 1 = PiCIE's cosine classifier
    within_weight: float = 0.5
    cross_weight: float = 0.5
    equiv_min_crop: float = 0.5  # G crops a side fraction drawn in [equiv_min_crop, 1] of the view

    def __post_init__(self):
        super().__post_init__()
        if self.cluster_every < 1:
            raise ValueError(f"cluster_every must be ≥ 1, got {self.cluster_every}")
        if not self.tau > 0 or self.within_weight < 0 or self.cross_weight < 0:
            raise ValueError(f"tau must be > 0 and the loss weights ≥ 0, got {self.tau}, {self.within_weight}, "
                             f"{self.cross_weight}")
        if not 0 < self.equiv_min_crop <= 1:
            raise ValueError(f"equiv_min_crop must be in (0, 1], got {self.equiv_min_crop}")


@dataclass(frozen=True)
class Geometric:
    """PiCIE's equivariance transform G: crop ``box`` = (y0, y1, x0, x1) (pixels, half-open), resize
    back to the input size, then flip horizontally if ``flip``."""

    box: tuple[int, int, int, int]
    flip: bool


def sample_geometric(h: int, w: int, min_crop: float, flip: bool, rng: np.random.Generator) -> Geometric:
    """A random G for an h×w view: the crop's sides are the same fraction in [min_crop, 1] of h and w."""
    s = rng.uniform(min_crop, 1.0)
    ch, cw = max(1, round(h * s)), max(1, round(w * s))
    y0, x0 = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
    return Geometric((y0, y0 + ch, x0, x0 + cw), bool(flip and rng.random() < 0.5))


def apply_geometric(t: torch.Tensor, g: Geometric, mode: str = "bilinear") -> torch.Tensor:
    """G applied to a C×H×W or B×C×H×W tensor (images, features, or masks as float with
    ``mode="nearest"``) → the same shape."""
    y0, y1, x0, x1 = g.box
    squeeze = t.ndim == 3
    x = t[None] if squeeze else t
    out = F.interpolate(x[..., y0:y1, x0:x1], size=x.shape[-2:], mode=mode,
                        **({} if mode == "nearest" else {"align_corners": False}))
    if g.flip:
        out = out.flip(-1)
    return out[0] if squeeze else out


def picie_loss(z1: torch.Tensor, z2: torch.Tensor, fg: torch.Tensor, mu1: torch.Tensor, mu2: torch.Tensor,
               tau: float, within_weight: float = 0.5, cross_weight: float = 0.5) -> torch.Tensor:
    """PiCIE's within-view and cross-view cluster classification loss over foreground pixels.

    z1, z2: B×D×H×W unit features of the two views (already aligned by G); fg: B×H×W bool; mu1, mu2:
    K×D centroids of each view. Labels y_v = argmax z_v·μ_v (no gradient). Zero-size foreground → 0.
    """
    a, b = z1.permute(0, 2, 3, 1)[fg], z2.permute(0, 2, 3, 1)[fg]  # N×D
    if len(a) == 0:
        return (z1.sum() + z2.sum()) * 0.0
    l11, l12, l21, l22 = a @ mu1.T / tau, a @ mu2.T / tau, b @ mu1.T / tau, b @ mu2.T / tau
    y1, y2 = l11.detach().argmax(1), l22.detach().argmax(1)
    within = F.cross_entropy(l11, y1) + F.cross_entropy(l22, y2)
    cross = F.cross_entropy(l12, y2) + F.cross_entropy(l21, y1)
    return within_weight * within + cross_weight * cross


def picie_views(frames: UnlabeledFrames, idx: list[int], cfg: PicieConfig, rng: np.random.Generator
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[Geometric]]:
    """The inputs of both views for frames ``idx``: (G(P1 x), P2 x, G(foreground), [G]).

    x is the frame after ``augment`` (foreground crop, scale, crop, flip; no colour); P1, P2 colour jitters.
    """
    plain, jitter = cfg.train.augment_config(jitter=False), cfg.train.augment_config()
    x1, x2, fgs, gs = [], [], [], []
    for i in idx:
        img, lab = augment(*frames[i], plain, rng)
        hwc = np.ascontiguousarray(img.transpose(1, 2, 0))
        p1, p2 = (torch.from_numpy(_jitter(hwc, jitter, rng).transpose(2, 0, 1).copy()) for _ in range(2))
        g = sample_geometric(*lab.shape, cfg.equiv_min_crop, cfg.train.flip, rng)
        x1.append(apply_geometric(p1, g))
        x2.append(p2)
        fgs.append(apply_geometric(torch.from_numpy(lab >= 0).float()[None], g, "nearest")[0] > 0.5)
        gs.append(g)
    return torch.stack(x1), torch.stack(x2), torch.stack(fgs), gs


def encode_views(net: nn.Module, x1: torch.Tensor, x2: torch.Tensor, gs: list[Geometric], speed: SpeedSettings
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """z1 = f(G(P1 x)) (x1 already transformed), z2 = G(f(P2 x)); the network runs as ``speed`` says, and the
    features come back in float32."""
    with speed.autocast(x1.device):
        z2 = net(speed.layout(x2)).float()  # P2's view first: batch norm's running statistics see it first
        z1 = net(speed.layout(x1)).float()
    return z1, torch.stack([apply_geometric(z, g) for z, g in zip(z2, gs)])


def cluster_views(net: nn.Module, frames: UnlabeledFrames, cfg: PicieConfig, step: int, device: torch.device
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """The epoch's centroids (μ1, μ2): k-means of each view's foreground features over all training frames."""
    rng = np.random.default_rng([cfg.train.seed, step, 1])
    gen = torch.Generator().manual_seed(cfg.train.seed * 1_000_003 + step)
    per_frame = max(1, cfg.kmeans_pixels // len(frames))
    rows1, rows2 = [], []
    net.eval()
    with torch.no_grad():
        for start in range(0, len(frames), cfg.train.batch_size):
            x1, x2, fg, gs = picie_views(frames, list(range(start, min(start + cfg.train.batch_size, len(frames)))),
                                         cfg, rng)
            z1, z2 = encode_views(net, x1.to(device), x2.to(device), gs, cfg.train)
            for b in range(len(gs)):
                rows1.append(sample_pixels(z1[b:b + 1].cpu(), fg[b:b + 1], per_frame, gen))
                rows2.append(sample_pixels(z2[b:b + 1].cpu(), fg[b:b + 1], per_frame, gen))
    net.train()
    return tuple(spherical_kmeans(torch.cat(r), cfg.n_classes, cfg.kmeans_iters, gen).to(device)
                 for r in (rows1, rows2))


class Picie(SemanticMethodBase):
    """Baseline E: PiCIE from scratch (FPN features, k-means classes) → connected components per class."""

    name = "picie"
    config_cls = PicieConfig

    def train_model(self, frames: UnlabeledFrames, out_dir: Path, progress: bool = True
                    ) -> tuple[PicieNet, torch.Tensor]:
        return train_picie(frames, self.config, out_dir, progress)


def train_picie(frames: UnlabeledFrames, cfg: PicieConfig, out_dir: Path, progress: bool = True
                ) -> tuple[PicieNet, torch.Tensor]:
    """Train PiCIE into ``out_dir`` (resumable; a finished run is loaded) → (network, K test centroids)."""
    key = {"method": "picie", "config": training_key(cfg), "frames": len(frames)}
    weights = Path(out_dir) / WEIGHTS
    saved = finished(weights, key)
    if saved is None:
        device = begin_training(cfg.train)
        net = cfg.train.layout(PicieNet(cfg.net).to(device))
        opt = torch.optim.AdamW(net.parameters(), lr=cfg.train.lr, weight_decay=cfg.train.weight_decay)
        state = {"mu1": torch.zeros(cfg.n_classes, cfg.net.embed_dim, device=device),
                 "mu2": torch.zeros(cfg.n_classes, cfg.net.embed_dim, device=device)}

        def step_loss(step: int) -> torch.Tensor:
            if step % cfg.cluster_every == 0:
                state["mu1"], state["mu2"] = cluster_views(net, frames, cfg, step, device)
            rng = np.random.default_rng([cfg.train.seed, step])
            idx = rng.choice(len(frames), cfg.train.batch_size, replace=len(frames) < cfg.train.batch_size)
            x1, x2, fg, gs = picie_views(frames, [int(i) for i in idx], cfg, rng)
            z1, z2 = encode_views(net, x1.to(device), x2.to(device), gs, cfg.train)
            return picie_loss(z1, z2, fg.to(device), state["mu1"], state["mu2"], cfg.tau, cfg.within_weight,
                              cfg.cross_weight)

        train_loop(Path(out_dir), key, {"net": net}, opt, cfg.train, step_loss, state, desc="train picie",
                   progress=progress)
        centroids = final_centroids(net.eval(), frames, cfg.train, cfg, device)
        save_final(weights, key, net_cfg=to_dict(cfg.net), net=net.state_dict(), centroids=centroids.cpu())
        return net, centroids
    net = PicieNet(from_dict(PicieNetConfig, saved["net_cfg"]))
    net.load_state_dict(saved["net"])
    return net.eval(), saved["centroids"]
