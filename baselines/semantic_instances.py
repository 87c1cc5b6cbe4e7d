"""Shared parts of the unsupervised *semantic* baselines (PiCIE, STEGO) scored as instance methods.

Both methods learn per-pixel features without labels and cluster them into K classes. An instance
metric cannot score classes, so every class is split into its connected components, and
components smaller than ``min_component_px`` are absorbed by a neighbour or dropped: the same
post-processing (:func:`selfseg.method.meanshift.split_components` and ``absorb_small``, with the
same connectivity and minimum size defaults) as ``ours`` applies to its mean-shift clusters.

Training foreground: the methods are unlabeled, so the training frames' foreground comes from
their own depth: every frame's depth is back-projected, the support plane is found by RANSAC and
removed (:func:`selfseg.method.background.frame_foreground`, camera frame, no up hint: the
largest plane, oriented so that most other points lie above it), and the pixels of the points kept
above it are foreground. At test time the evaluator's ground-truth foreground mask is used, as for
every method. Only foreground pixels enter clustering and the losses.

Also here: spherical k-means, the training schedule shared by both methods and a resumable,
deterministic training loop (checkpoints of every module, optimizer and extra state tensor).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from tqdm import tqdm

from selfseg.config import to_dict
from selfseg.dataset import Video
from selfseg.fileio import hash_json, write_json
from selfseg.method.background import BackgroundConfig, frame_foreground
from selfseg.method.embed_method import video_key
from selfseg.method.features import embed_frames, foreground_box
from selfseg.method.meanshift import MeanShiftConfig, absorb_small, split_components
from selfseg.method.train import (TRAINING_LOG_JSON, OptimSchedule, SpeedSettings, TrainConfig,
                                  _latest_checkpoint, _save_checkpoint, _save_torch, drop_checkpoints, resolve_device,
                                  settings_key)
from selfseg.method_api import Method

TRAIN_DIR = "{method}-{key_hash}"  # in the method's workdir: its training run (files: selfseg.method.train)


@dataclass
class Schedule(OptimSchedule, SpeedSettings):
    """Optimisation and augmentation of one training phase (sizes in pixels, H × W).

    Frames are first cropped to their foreground box grown by ``fg_crop_margin`` × its longer side
    (``fg_crop``), resized so the longer side is ``image_size``, randomly rescaled, cropped to
    ``crop`` and flipped (:func:`selfseg.method.train.augment`); colour jitter is the methods'.
    """

    image_size: int = 160
    crop: tuple[int, ...] = (96, 128)
    scale_range: tuple[float, ...] = (0.75, 1.25)
    flip: bool = True
    brightness: float = 0.3
    contrast: float = 0.3
    saturation: float = 0.3
    hue: float = 0.05
    fg_crop: bool = True
    fg_crop_margin: float = 0.1

    def __post_init__(self):
        super().__post_init__()
        if self.image_size < 16:
            raise ValueError(f"image_size must be ≥ 16, got {self.image_size}")
        self.check_speed()
        self.augment_config()  # validates crop, scale_range and fg_crop_margin

    def augment_config(self, jitter: bool = True) -> TrainConfig:
        """These settings as the :class:`TrainConfig` that ``augment`` and ``_jitter`` read (no jitter
        if ``jitter`` is False: the methods jitter their views themselves)."""
        colour = dict(brightness=self.brightness, contrast=self.contrast, saturation=self.saturation, hue=self.hue)
        if not jitter:
            colour = dict.fromkeys(colour, 0.0)
        return TrainConfig(steps=self.steps, batch_size=self.batch_size, image_size=self.image_size,
                           crop=tuple(self.crop), scale_range=tuple(self.scale_range), flip=self.flip,
                           fg_crop=self.fg_crop, fg_crop_margin=self.fg_crop_margin, min_segment_px=0,
                           seed=self.seed, **colour)


@dataclass
class SemanticConfig:
    """Settings shared by the semantic baselines: classes, clustering, instances, training data."""

    n_classes: int = 8  # K, the number of k-means classes at test time
    kmeans_iters: int = 30
    kmeans_pixels: int = 50000  # k-means runs on at most this many random foreground pixels
    # class → instances: as ours' post-processing (MeanShiftConfig), whose defaults these are
    min_component_px: int = MeanShiftConfig.min_component_px
    connectivity: int = MeanShiftConfig.connectivity
    # "components": every class split into connected components (the default, see the module docstring);
    # "classes": each class inside the foreground is one segment (no split), to show what the split adds
    instances: Literal["components", "classes"] = "components"
    frame_stride: int = 3  # training uses every n-th frame of each training video
    background: BackgroundConfig = field(default_factory=BackgroundConfig)  # training-frame foreground
    device: str = "auto"  # inference device

    def __post_init__(self):
        if self.n_classes < 1:
            raise ValueError(f"n_classes (K) must be ≥ 1, got {self.n_classes}")
        if self.kmeans_iters < 1 or self.kmeans_pixels < 1:
            raise ValueError(f"kmeans_iters and kmeans_pixels must be ≥ 1, got {self.kmeans_iters} and "
                             f"{self.kmeans_pixels}")
        if self.min_component_px < 0 or self.connectivity not in (4, 8):
            raise ValueError(f"min_component_px must be ≥ 0 and connectivity 4 or 8, got {self.min_component_px} "
                             f"and {self.connectivity}")
        if self.frame_stride < 1:
            raise ValueError(f"frame_stride must be ≥ 1, got {self.frame_stride}")


class UnlabeledFrames:
    """Training frames with their own foreground masks, loaded once: ``frames[i]`` → (rgb uint8 H×W×3,
    labels int32 H×W with 0 = foreground, −1 = background), the pair format of ``augment``."""

    def __init__(self, videos: list[Video], frame_stride: int, bg: BackgroundConfig, progress: bool = True):
        items = [(v, f) for v in videos for f in v.frame_ids[::frame_stride]]
        if not items:
            raise ValueError("no training frames")
        self.rgb, self.labels = [], []
        for v, f in tqdm(items, desc="training foreground", unit="frame", disable=not progress, leave=False):
            self.rgb.append(v.rgb(f))
            fg = frame_foreground(v.depth_m(f), v.K(f), bg, f"video {v.video_id} frame {f}")
            self.labels.append(np.where(fg, 0, -1).astype(np.int32))

    def __len__(self) -> int:
        return len(self.rgb)

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        return self.rgb[i], self.labels[i]


def kmeans_init(x: torch.Tensor, k: int, gen: torch.Generator) -> torch.Tensor:
    """k-means++ seeds (cosine distance 1 − x·c) of unit rows ``x`` (N×D) → k×D (repeats if N < k)."""
    first = int(torch.randint(len(x), (1,), generator=gen))
    centres = [x[first]]
    dist = (1 - x @ x[first]).clamp_min(0)
    for _ in range(1, k):
        total = dist.sum()
        i = int(torch.multinomial(dist / total, 1, generator=gen)) if total > 0 else \
            int(torch.randint(len(x), (1,), generator=gen))
        centres.append(x[i])
        dist = torch.minimum(dist, (1 - x @ x[i]).clamp_min(0))
    return torch.stack(centres)


def spherical_kmeans(x: torch.Tensor, k: int, iters: int, gen: torch.Generator) -> torch.Tensor:
    """Cluster unit vectors ``x`` (N×D) by cosine similarity → unit centroids k×D.

    k-means++ seeding, then ``iters`` rounds of: assign to the most similar centroid, centroid =
    normalised mean; an empty cluster is re-seeded at the point least similar to its centroid.
    """
    if len(x) == 0:
        raise ValueError("k-means needs at least one foreground pixel")
    x = F.normalize(x.float(), dim=1)
    c = kmeans_init(x, k, gen)
    for _ in range(iters):
        sim = x @ c.T
        lab = sim.argmax(1)
        sums = torch.zeros_like(c).index_add_(0, lab, x)
        counts = torch.bincount(lab, minlength=k)
        for j in torch.nonzero(counts == 0).flatten().tolist():
            far = int(sim.max(1).values.argmin())
            sums[j] = x[far]
            sim[far] = 2.0  # not picked twice
        new = F.normalize(sums, dim=1)
        if torch.equal(new, c):
            break
        c = new
    return c


def classes_to_instances(classes: np.ndarray, fg_mask: np.ndarray, connectivity: int, min_px: int) -> np.ndarray:
    """Class map (int H×W, values ≥ 0) → instance map int32 H×W (0 = background, 1..n): every class
    inside ``fg_mask`` split into its connected components, components below ``min_px`` absorbed by
    the neighbour sharing the longest border or dropped (ours' post-processing)."""
    labels = np.where(np.asarray(fg_mask, bool), np.asarray(classes) + 1, 0)
    return absorb_small(split_components(labels, connectivity), min_px)


def poly_lr(opt: torch.optim.Optimizer, base_lr: float, step: int, steps: int) -> None:
    """Polynomial decay (power 0.9) to 0, as :func:`selfseg.method.train.train_embedding`."""
    for g in opt.param_groups:
        g["lr"] = base_lr * (1 - step / steps) ** 0.9


def train_loop(out_dir: Path, key: dict, modules: dict[str, nn.Module], opt: torch.optim.Optimizer,
               sched: Schedule, step_loss: Callable[[int], torch.Tensor], state: dict[str, torch.Tensor],
               after_step: Callable[[int], None] | None = None, desc: str = "train", progress: bool = True
               ) -> list[float]:
    """Run steps ``0 … sched.steps − 1`` of one training phase, resumably; returns the losses.

    ``step_loss(step)`` returns the loss of a step, a pure function of (seed, step, weights, ``state``);
    ``after_step(step)`` runs after the optimizer step (e.g. a teacher's EMA); ``state`` holds extra
    tensors the steps update in place (centroids, a centre), saved and restored with the modules'
    weights and the optimizer in ``out_dir/checkpoints/step_NNNNNN.pt`` (only the latest kept).
    A checkpoint with another ``key`` raises ValueError. ``training_log.json`` records the losses.
    """
    key_hash = hash_json(key)
    start, losses = 0, []
    latest = _latest_checkpoint(out_dir)
    if latest is not None:
        saved = torch.load(latest, map_location="cpu", weights_only=True)
        if saved["key_hash"] != key_hash:
            raise ValueError(f"{latest}: checkpoint has other training settings; use another out_dir or delete it")
        for name, m in modules.items():
            m.load_state_dict(saved["modules"][name])
        opt.load_state_dict(saved["optimizer"])
        for name, t in saved["state"].items():
            state[name] = t.to(state[name].device) if name in state and torch.is_tensor(state[name]) else t
        start, losses = int(saved["step"]), list(saved["losses"])
    for m in modules.values():
        m.train()
    t0 = time.perf_counter()
    bar = tqdm(range(start, sched.steps), initial=start, total=sched.steps, disable=not progress, desc=desc,
               dynamic_ncols=True)
    for step in bar:
        poly_lr(opt, sched.lr, step, sched.steps)
        loss = step_loss(step)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if after_step is not None:
            after_step(step)
        losses.append(loss.item())
        if not np.isfinite(losses[-1]):
            raise FloatingPointError(f"{desc}: loss became {losses[-1]} at step {step}; lower lr (now {sched.lr})")
        bar.set_postfix(loss=f"{losses[-1]:.4f}")
        done = step + 1
        if done % sched.checkpoint_every == 0 or done == sched.steps:
            _save_checkpoint(out_dir, done, {"step": done, "modules": {n: m.state_dict() for n, m in modules.items()},
                                             "optimizer": opt.state_dict(), "state": dict(state), "losses": losses,
                                             "key_hash": key_hash})
            write_json(out_dir / TRAINING_LOG_JSON, {
                "phase": desc, "key": key, "steps": len(losses), "loss": losses,
                "final_loss_mean10": float(np.mean(losses[-10:])),
                "seconds_this_session": round(time.perf_counter() - t0, 2),
                "s_per_step": round((time.perf_counter() - t0) / max(done - start, 1), 4),
                "threads": torch.get_num_threads()})
    bar.close()
    return losses


def finished(weights: Path, key: dict) -> dict | None:
    """The saved final state at ``weights`` if it was trained with ``key``; None if absent; raises if
    it was trained with other settings."""
    if not weights.is_file():
        return None
    saved = torch.load(weights, map_location="cpu", weights_only=True)
    if saved["key_hash"] != hash_json(key):
        raise ValueError(f"{weights}: trained with other settings; use another out_dir or delete it")
    return saved


class SemanticMethodBase(Method):
    """Unsupervised semantic features + k-means classes → connected-component instances.

    Configs have a ``train`` :class:`Schedule` (the segmenting network's). Subclasses implement
    :meth:`train_model`, which returns the network (forward: B×3×H×W in [0, 1] →
    B×D×H×W unit features, with ``net.cfg.embed_dim`` = D) and the K unit class centroids.
    """

    needs_fit = True
    needs_ground_truth = False

    def __init__(self, config=None, workdir: str | Path | None = None):
        super().__init__(config, workdir)
        self._device = resolve_device(self.config.device)
        self._net: nn.Module | None = None
        self._centroids: torch.Tensor | None = None

    def train_model(self, frames: UnlabeledFrames, out_dir: Path) -> tuple[nn.Module, torch.Tensor]:
        raise NotImplementedError

    def fit(self, train_videos: list[Video]) -> None:
        if self.workdir is None:
            raise ValueError(f"method {self.name!r} needs a workdir to store its trained network")
        cfg = self.config
        frames = UnlabeledFrames(train_videos, cfg.frame_stride, cfg.background)
        key = {"method": self.name, "config": training_key(cfg), "data": [video_key(v) for v in train_videos]}
        out_dir = self.workdir / TRAIN_DIR.format(method=self.name, key_hash=hash_json(key))
        net, centroids = self.train_model(frames, out_dir)
        self._net = net.to(self._device).eval()
        self._centroids = centroids.to(self._device)

    def features(self, rgb: np.ndarray, fg_mask: np.ndarray) -> torch.Tensor:
        """uint8 H×W×3 → D×H×W unit features at the training scale (inside the foreground box with
        ``fg_crop``, zero outside it)."""
        if self._net is None:
            raise RuntimeError(f"method {self.name!r} has no trained network: call fit() first")
        sched = self.config.train  # the segmenting network's schedule: its scale and foreground crop
        boxes = [foreground_box(fg_mask, sched.fg_crop_margin)] if sched.fg_crop else None
        return embed_frames(self._net, [rgb], self._device, sched.image_size, boxes)[0]

    def segment(self, video: Video, frame_id: int, fg_mask: np.ndarray) -> np.ndarray:
        fg = np.asarray(fg_mask, bool)
        emb = self.features(video.rgb(frame_id), fg)
        classes = torch.einsum("dhw,kd->khw", emb, self._centroids).argmax(0).cpu().numpy()
        if self.config.instances == "classes":
            return np.where(fg, classes + 1, 0).astype(np.int32)
        return classes_to_instances(classes, fg, self.config.connectivity, self.config.min_component_px)


def sample_pixels(feats: torch.Tensor, fg: torch.Tensor, n: int, gen: torch.Generator) -> torch.Tensor:
    """At most ``n`` random foreground rows of B×D×H×W features with a B×H×W bool mask → M×D."""
    rows = feats.permute(0, 2, 3, 1)[fg]
    if len(rows) > n:
        rows = rows[torch.randperm(len(rows), generator=gen)[:n]]
    return rows


def final_centroids(net: nn.Module, frames: UnlabeledFrames, sched: Schedule, cfg: SemanticConfig,
                    device: torch.device) -> torch.Tensor:
    """The K test-time class centroids: spherical k-means of the trained network's foreground features
    over all training frames, each embedded as at test time (foreground box, ``image_size``)."""
    gen = torch.Generator().manual_seed(sched.seed)
    per_frame = max(1, cfg.kmeans_pixels // len(frames))
    rows = []
    for rgb, lab in frames:
        fg = lab >= 0
        boxes = [foreground_box(fg, sched.fg_crop_margin)] if sched.fg_crop else None
        emb = embed_frames(net, [rgb], device, sched.image_size, boxes).cpu()
        rows.append(sample_pixels(emb, torch.from_numpy(fg)[None], per_frame, gen))
    return spherical_kmeans(torch.cat(rows), cfg.n_classes, cfg.kmeans_iters, gen)


def save_final(path: Path, key: dict, **tensors: Any) -> None:
    """Atomically save the final state of a method (state dicts, centroids) under its key, then delete the
    resumable checkpoints of its folder."""
    _save_torch(path, {"key_hash": hash_json(key), **tensors})
    drop_checkpoints(path.parent)


def training_key(cfg: SemanticConfig) -> dict:
    """What a method's training depends on: its config without runtime and test-time-only fields
    (the class → instance post-processing), so changing those reuses the trained network."""
    return {k: v for k, v in result_key(cfg).items() if k not in ("min_component_px", "connectivity", "instances")}


def result_key(cfg: Any) -> Any:
    """A config as JSON without the fields that change how a run executes but not its result (at any depth)."""
    return settings_key(to_dict(cfg))

