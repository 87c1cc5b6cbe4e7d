"""One trainer for every pixel-embedding network: φ1, φ2, the supervised upper bound and V1.

The trainer never opens ground truth itself: it reads (RGB, label map) pairs from the *label
source* it is handed. Every step's batch and augmentation come from ``np.random.default_rng
([seed, step])`` and the weights from ``torch.manual_seed(seed)``, so a run is deterministic and a
run resumed from a checkpoint reproduces an unbroken one (bitwise on the CPU).

Reproducibility: results are bitwise identical for the same commit, data, seed and ``threads`` on the
same machine. The thread count is part of that: float reductions split across threads sum in another
order (measured on tiny: 1 and 2 threads give different losses from step 1 and IoU .684 vs .716 after
20 steps), so ``threads`` defaults to 1 rather than torch's default, which depends on the core count
and ``OMP_NUM_THREADS``. :func:`begin_training` applies it, and it stays set for the inference that
follows in the same process (evaluate's method process).

Files in ``out_dir`` (templates below, shared by the baselines' trainers): ``checkpoints/step_NNNNNN.pt``
(only the latest is kept; deleted once ``weights.pt`` is written), ``weights.pt`` (final; a finished run is not retrained), ``training_log.json``
and ``loss_curve.png``.
``out_dir`` must be specific to the label source: the trainer cannot tell two sources apart.
"""
from __future__ import annotations

import io
import os
import shutil
import sys
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Iterator, Protocol, Sequence

import cv2
import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from selfseg.config import from_dict, to_dict
from selfseg.dataset import Video
from selfseg.fileio import atomic_write_bytes, hash_json, write_json
from selfseg.method.contrastive import NEGATIVES, prototype_contrastive_loss
from selfseg.method.features import NORMAL_X, foreground_box, input_fill, video_frame
from selfseg.method.network import EmbeddingNet, NetConfig

# Files of a training run, relative to its out_dir.
WEIGHTS = "weights.pt"  # the final network (torch dict with the settings' key_hash); a finished run is not retrained
CHECKPOINT_PT = "checkpoints/step_{step:06d}.pt"  # resumable state after `step` optimizer steps (only the latest kept)
TRAINING_LOG_JSON = "training_log.json"  # settings, per-step losses, session seconds and throughput; at each checkpoint
LOSS_CURVE_PNG = "loss_curve.png"  # plot of the per-step loss and its running mean
# Settings that change how a run executes but not its result; excluded from the resume key.
_RUNTIME_FIELDS = ("device", "threads", "checkpoint_every")
PREFETCH_THREADS = 6  # most threads making batches ahead of a GPU's steps (training_batches)
PRECISIONS = ("fp32", "bf16", "auto")  # TrainConfig.precision: the dtype of the network's forward pass in training


@dataclass
class OptimSchedule:
    """Optimisation of one training phase, shared by the baselines' trainers: AdamW with polynomial
    decay (power 0.9) to 0 over ``steps`` batches of ``batch_size``."""

    steps: int = 1000
    batch_size: int = 8
    lr: float = 1e-3
    weight_decay: float = 1e-4
    seed: int = 0
    checkpoint_every: int = 200
    device: str = "auto"  # "auto" → cuda if available, else cpu
    threads: int = 1  # torch CPU threads; results are identical for the same value; 0 = torch's default
    # (core count or OMP_NUM_THREADS: not reproducible across environments)

    def __post_init__(self):
        if self.steps < 1 or self.batch_size < 1 or self.checkpoint_every < 1:
            raise ValueError(f"steps, batch_size and checkpoint_every must be ≥ 1, got {self.steps}, "
                             f"{self.batch_size} and {self.checkpoint_every}")
        if not self.lr > 0 or self.weight_decay < 0:
            raise ValueError(f"lr must be > 0 and weight_decay ≥ 0, got {self.lr} and {self.weight_decay}")


@dataclass
class SpeedSettings:
    """How a training phase's network runs (docs/benchmarks.md); a trainer that has them honours both.

    ``channels_last``: the network's weights and input in NHWC memory layout (oneDNN's faster convolutions on the
    CPU; the same sums in another order). ``precision`` "bf16": the network's forward pass under bfloat16
    autocast (CPUs with AVX512-BF16 or AMX, and GPUs, run it about twice as fast; a CPU without them emulates it,
    11-14× slower than float32 on an AVX2 AMD EPYC); "auto": bf16 where the device runs it natively
    (:func:`native_bf16`), else float32. The features' upsampling and normalisation and the loss stay in float32."""

    channels_last: bool = False
    precision: str = "fp32"

    def check_speed(self) -> None:
        """Refuse an unknown precision; warn at once (as the config is read) of a bf16 the device would emulate."""
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {self.precision!r}")
        if self.precision == "bf16":
            _warn_if_emulated(resolve_device(getattr(self, "device", "auto")))

    def precision_on(self, device: torch.device) -> str:
        """The precision the phase trains in on ``device``: "fp32" or "bf16" ("auto" resolved)."""
        return resolve_precision(self.precision, device)

    def autocast(self, device: torch.device):
        """The context of the network's forward pass in training (bfloat16 autocast, or nothing)."""
        bf16 = self.precision_on(device) == "bf16"
        if bf16:
            _warn_if_emulated(device)
        return torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16)

    def layout(self, x: torch.Tensor | nn.Module):
        """``x`` (a network or a B×C×H×W batch) in the memory layout the phase trains in."""
        if not self.channels_last:
            return x
        return x.to(memory_format=torch.channels_last) if isinstance(x, nn.Module) else \
            x.contiguous(memory_format=torch.channels_last)


def resolve_precision(precision: str, device: torch.device) -> str:
    """``precision`` as it trains on ``device``: "auto" → "bf16" where :func:`native_bf16`, else "fp32"."""
    if precision == "auto":
        return "bf16" if native_bf16(device) else "fp32"
    return precision


def native_bf16(device: torch.device) -> bool:
    """Whether ``device`` runs bfloat16 convolutions natively: a CUDA GPU with bf16, or a CPU with AVX512-BF16 or
    AMX. Elsewhere oneDNN emulates them (measured: 11-14× slower than float32 on an AVX2 AMD EPYC)."""
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported(including_emulation=False)
    return device.type == "cpu" and (torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported())


_WARNED: set[str] = set()  # devices _warn_if_emulated has warned about in this process


def _warn_if_emulated(device: torch.device) -> None:
    """One warning line on stderr (per process and device) when bf16 training on ``device`` would be emulated."""
    if native_bf16(device) or str(device) in _WARNED:
        return
    _WARNED.add(str(device))
    what = f"cpu (torch capability {torch.backends.cpu.get_cpu_capability()})" if device.type == "cpu" else str(device)
    print(f"warning: precision bf16 on a {what} without native bfloat16: emulated and slow (11-14× float32's step on "
          f"an AVX2 CPU); precision 'auto' trains in float32 on such a device", file=sys.stderr, flush=True)


def settings_key(d):
    """A config's dict (:func:`to_dict`) as a training run's resume key: without the fields that change how a run
    executes but not its result (at any depth), and precision "auto" replaced by the precision it resolves to on
    the settings' device, so an "auto" run equals the explicit run of that precision."""
    if not isinstance(d, dict):
        return d
    if d.get("precision") == "auto":
        d = {**d, "precision": resolve_precision("auto", resolve_device(d.get("device", "auto")))}
    return {k: settings_key(v) for k, v in d.items() if k not in _RUNTIME_FIELDS}


@dataclass
class TrainConfig(OptimSchedule, SpeedSettings):
    """Training schedule (:class:`OptimSchedule`) and augmentation. Crop sizes in pixels (H, W), after
    resizing and scaling."""

    image_size: int = 320  # frames are first resized so their longer side is this (0 = keep)
    crop: tuple[int, ...] = (192, 256)  # random crop H, W (padded with ignore if the image is smaller)
    scale_range: tuple[float, ...] = (0.75, 1.25)  # random rescale factor before cropping
    flip: bool = True  # random horizontal flip
    brightness: float = 0.3  # colour jitter: factors drawn in [1 − x, 1 + x]
    contrast: float = 0.3
    saturation: float = 0.3
    hue: float = 0.05  # hue shift, fraction of the full hue circle, drawn in [−x, x]
    rotation_deg: float = 0.0  # random in-plane rotation about the crop's centre, drawn in [−x, x] degrees
    min_segment_px: int = 16  # segments with fewer pixels in a crop are ignored
    # Foreground crop: each frame is first cropped to the bounding box of its labelled pixels grown by
    # fg_crop_margin × its longer side, so image_size sets the scale of the objects, not of the room
    # around them. Inference crops to the given foreground mask the same way (features.embed_frames).
    fg_crop: bool = False
    fg_crop_margin: float = 0.1
    # Background masked out of the input: every pixel outside the foreground (the label source's
    # foreground mask, else its labelled pixels) and the padding is set to the network's input mean
    # (network.RGB_MEAN) after colour jitter, and labels outside the foreground are ignored. The foreground
    # then also sets the crop box. Inference masks the same way with the mask it is given (embed_frames).
    mask_background: bool = False
    # Scope of the contrastive negatives (method.contrastive): "image" is the paper's (the segments of the
    # pixel's own frame). "batch" pushes the same object in two frames of a batch apart; measured: it
    # collapsed supervised embeddings at 2000 steps on tiny and gave φ1 lower same-object cosine across
    # scenes (median .51 vs .72); docs/choices.md. "global": label ids name the same
    # object in every frame (one prototype per object over the batch); only for label sources with global ids.
    # "video" ([selfseg]): ids name one 3-D segment in every frame of its video; its views in a batch share a
    # prototype, and only the segments of the same video are negatives (needs frames_per_video ≥ 2).
    negatives: str = "image"
    # Frames drawn from each video in a batch (batch_size must be a multiple): 1 = every frame drawn
    # independently of its video (the paper's sampling); k > 1: batch_size / k videos, k frames each.
    frames_per_video: int = 1
    tau: float = 0.07
    loss_pixels: int = 50000  # the loss averages over at most this many random labelled pixels (0 = all)
    def __post_init__(self):
        super().__post_init__()
        if len(self.crop) != 2 or min(self.crop) < 16:
            raise ValueError(f"crop must be (H, W) with both ≥ 16, got {self.crop}")
        if len(self.scale_range) != 2 or not 0 < self.scale_range[0] <= self.scale_range[1]:
            raise ValueError(f"scale_range must be (lo, hi) with 0 < lo ≤ hi, got {self.scale_range}")
        if self.negatives not in NEGATIVES:
            raise ValueError(f"negatives must be one of {NEGATIVES}, got {self.negatives!r}")
        if self.frames_per_video < 1 or self.batch_size % self.frames_per_video:
            raise ValueError(f"frames_per_video must be ≥ 1 and divide batch_size {self.batch_size}, "
                             f"got {self.frames_per_video}")
        if self.negatives == "video" and self.frames_per_video < 2:
            raise ValueError("negatives 'video' needs frames_per_video ≥ 2 (else no segment has two views in a "
                             "batch)")
        if self.fg_crop_margin < 0:
            raise ValueError(f"fg_crop_margin must be ≥ 0, got {self.fg_crop_margin}")
        if not 0 <= self.rotation_deg <= 180:
            raise ValueError(f"rotation_deg must be in [0, 180], got {self.rotation_deg}")
        self.check_speed()

    @property
    def crop_margin(self) -> float | None:
        """The foreground-crop margin if ``fg_crop`` is on, else None (what inference passes on)."""
        return self.fg_crop_margin if self.fg_crop else None

    @classmethod
    def preset(cls, name: str, **overrides) -> "TrainConfig":
        """Named schedule ("tiny": a minute-scale run for the tiny preset and tests; "default": CPU)."""
        if name not in TRAIN_PRESETS:
            raise ValueError(f"unknown training preset {name!r}; choose one of {sorted(TRAIN_PRESETS)}")
        return cls(**{**TRAIN_PRESETS[name], **overrides})


# "default": 8000 crops of 192×256, about 15 min for the "fast" network on 2 free CPU cores
# (bench/bench_inference.py measured 10 images/s), several hours for the full-width one.
TRAIN_PRESETS: dict[str, dict] = {
    "tiny": dict(steps=150, batch_size=4, image_size=160, crop=(96, 128), checkpoint_every=50),
    "default": {},
}


class LabelSource(Protocol):
    """Training pairs: ``source[i]`` → (input frame: uint8 H×W×3 RGB or a geometry frame, see
    :mod:`selfseg.method.features`; labels int32 H×W, −1 = ignore, ≥ 0 = segment id).

    Optional attributes the trainer reads: ``foreground(i)`` → bool H×W foreground mask of pair i or None
    (``TrainConfig.mask_background``; without it, the labelled pixels), and ``global_ids``: True when an id
    names the same object in every frame (required by ``negatives: global``); ``group(i)`` → the video
    of pair i (required by ``frames_per_video`` > 1); ``geometry``: True when its frames carry the geometry channels
    (must match ``NetConfig.geometry``; without the attribute, RGB)."""

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]: ...


LabelLoader = Callable[[Video, int], np.ndarray]
MaskLoader = Callable[[Video, int], np.ndarray]


class FrameLabelSource:
    """Frames of videos with a label map each, read lazily.

    items: (video, frame_id, loader) triples; ``loader(video, frame_id)`` returns the frame's int
    label map (−1 = ignore, ≥ 0 = segment id), e.g. projected 3D segments or pseudo-labels.
    ``foreground``: optional loader of the frame's bool foreground mask (the method's own, for
    ``TrainConfig.mask_background``). ``global_ids``: the loaders' ids name the same object in every
    video (object identities), not segments of one scene. ``geometry``: the frames carry the geometry channels
    (:func:`selfseg.method.features.video_frame`; for a network with ``NetConfig.geometry``).
    """

    def __init__(self, items: Sequence[tuple[Video, int, LabelLoader]], foreground: MaskLoader | None = None,
                 global_ids: bool = False, geometry: bool = False):
        self.items = list(items)
        if not self.items:
            raise ValueError("a label source needs at least one frame")
        self._foreground = foreground
        self.global_ids = global_ids
        self.geometry = geometry

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        video, fid, loader = self.items[i]
        frame = video_frame(video, fid, self.geometry)
        labels = np.asarray(loader(video, fid))
        if labels.shape != frame.shape[:2] or not np.issubdtype(labels.dtype, np.integer):
            raise ValueError(f"video {video.video_id} frame {fid}: label map must be an integer "
                             f"{frame.shape[0]}×{frame.shape[1]} array, got {labels.dtype} {labels.shape}")
        return frame, labels.astype(np.int32)

    def foreground(self, i: int) -> np.ndarray | None:
        """bool H×W foreground mask of pair ``i`` from the ``foreground`` loader; None without one."""
        if self._foreground is None:
            return None
        video, fid, _ = self.items[i]
        fg = np.asarray(self._foreground(video, fid))
        if fg.shape != (video.height, video.width):
            raise ValueError(f"video {video.video_id} frame {fid}: foreground mask must be "
                             f"{video.height}×{video.width}, got {fg.shape}")
        return fg.astype(bool)

    def group(self, i: int) -> str:
        """The video of pair ``i`` (its video id)."""
        return self.items[i][0].video_id


def batch_items(source: LabelSource, cfg: TrainConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of one batch and each one's video: (indices, B long group index within the batch).

    ``frames_per_video`` = 1: ``batch_size`` pairs drawn at random (groups: 0..B−1, each image its own);
    k > 1: batch_size / k videos, then k frames of each (without replacement where there are enough)."""
    k = cfg.frames_per_video
    if k == 1:
        idx = rng.choice(len(source), cfg.batch_size, replace=len(source) < cfg.batch_size)
        return idx, np.arange(cfg.batch_size)
    if not hasattr(source, "group"):
        raise ValueError("frames_per_video > 1 needs a label source that names each pair's video (group)")
    by_video: dict = {}
    for i in range(len(source)):
        by_video.setdefault(source.group(i), []).append(i)
    videos = sorted(by_video)
    n = cfg.batch_size // k
    picked = rng.choice(len(videos), n, replace=len(videos) < n)
    idx = [int(j) for v in picked for j in rng.choice(by_video[videos[v]], k, replace=len(by_video[videos[v]]) < k)]
    return np.asarray(idx), np.repeat(np.arange(n), k)


def begin_training(sched: TrainConfig | OptimSchedule) -> torch.device:
    """Threads, deterministic kernels and the weight seed of a training phase; returns its device.

    ``sched.threads`` > 0 sets torch's CPU threads (kept for the rest of the process); deterministic
    cuDNN and cuBLAS kernels on a GPU (not measured: no GPU was available when this was written)."""
    if sched.threads > 0:
        torch.set_num_threads(sched.threads)
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")  # read when cuBLAS starts: deterministic GEMMs
    torch.backends.cudnn.benchmark = False
    torch.backends.cudnn.deterministic = True
    torch.manual_seed(sched.seed)
    return resolve_device(sched.device)


def resolve_device(device: str) -> torch.device:
    """"auto" → cuda if available, else cpu; anything else is passed to torch."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def _jitter(img: np.ndarray, cfg: TrainConfig, rng: np.random.Generator) -> np.ndarray:
    """Colour jitter of float32 RGB in [0, 1] (brightness, contrast, saturation, hue; fixed order; H×W×3)."""
    gray_w = np.array([0.299, 0.587, 0.114], np.float32)
    img = img * np.float32(rng.uniform(1 - cfg.brightness, 1 + cfg.brightness))
    c = np.float32(rng.uniform(1 - cfg.contrast, 1 + cfg.contrast))
    img = (img - (img @ gray_w).mean()) * c + (img @ gray_w).mean()
    s = np.float32(rng.uniform(1 - cfg.saturation, 1 + cfg.saturation))
    gray = (img @ gray_w)[..., None]
    img = np.clip(gray + (img - gray) * s, 0, 1)
    hue = rng.uniform(-cfg.hue, cfg.hue)
    if hue != 0:
        hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV)  # float input: H in degrees [0, 360)
        hsv[..., 0] = (hsv[..., 0] + np.float32(hue * 360.0)) % 360.0
        img = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    return np.clip(img, 0, 1)


def _by_3_channels(img: np.ndarray, op: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """``op`` (an OpenCV image operation, some of which take at most 4 channels) on H×W×C ``img`` 3 channels at a
    time, restacked to h×w×C."""
    if img.shape[2] == 3:
        return op(img)
    return np.dstack([op(np.ascontiguousarray(img[..., c:c + 3])) for c in range(0, img.shape[2], 3)])


def _rotate(img: np.ndarray, lab: np.ndarray, fg: np.ndarray, deg: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotate image (linear, 0 outside), labels (nearest, −1 outside) and foreground (nearest, False
    outside) by ``deg`` degrees about the image centre, keeping the size; a geometry frame's normals turn with it."""
    h, w = lab.shape
    M = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), deg, 1.0)
    img = _by_3_channels(img, lambda x: cv2.warpAffine(x, M, (w, h), flags=cv2.INTER_LINEAR,
                                                       borderMode=cv2.BORDER_CONSTANT, borderValue=0))
    if img.shape[2] > 3:  # the normal's image-plane part (x, y) turns as pixel directions do
        img[..., NORMAL_X:NORMAL_X + 2] = img[..., NORMAL_X:NORMAL_X + 2] @ M[:, :2].T.astype(np.float32)
    lab = cv2.warpAffine(lab, M, (w, h), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=-1)
    fg = cv2.warpAffine(fg.astype(np.uint8), M, (w, h), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                        borderValue=0) > 0
    return img, lab, fg


def augment(frame: np.ndarray, labels: np.ndarray, cfg: TrainConfig, rng: np.random.Generator,
            fg: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Resize, random scale, rotation, crop, flip and colour jitter (of the RGB channels); with
    ``cfg.mask_background``, the background (outside ``fg``, bool H×W, or outside the labelled pixels if None) and
    padding set to :func:`~selfseg.method.features.input_fill` and its labels ignored.

    frame (uint8 H×W×3 RGB, or a float32 H×W×C geometry frame: :mod:`selfseg.method.features`), labels int H×W →
    (float32 C×h×w, RGB in [0, 1]; int64 h×w with −1 = ignore), h×w = cfg.crop. Padding (a scaled frame smaller than
    the crop) and pixels rotated in from outside get label −1. A mirrored geometry frame's normal x is negated.
    """
    img = frame.astype(np.float32) / 255.0 if frame.dtype == np.uint8 else frame.astype(np.float32)  # a copy
    fill = input_fill(img.shape[2])
    lab = labels.astype(np.int32)
    fgm = (lab >= 0 if fg is None else np.asarray(fg, bool)) if cfg.mask_background else lab >= 0
    box = foreground_box(fgm, cfg.fg_crop_margin) if cfg.fg_crop else None
    if box is not None:
        y0, y1, x0, x1 = box
        img, lab, fgm = img[y0:y1, x0:x1], lab[y0:y1, x0:x1], fgm[y0:y1, x0:x1]
    if cfg.mask_background:  # before resizing too, so that no background blends into the object's edge
        img[~fgm] = fill
    h, w = lab.shape
    base = cfg.image_size / max(h, w) if cfg.image_size > 0 else 1.0
    s = base * rng.uniform(*cfg.scale_range)
    nh, nw = max(1, round(h * s)), max(1, round(w * s))
    img = _by_3_channels(img, lambda x: cv2.resize(x, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else
                                                   cv2.INTER_LINEAR))  # antialiased
    lab = cv2.resize(lab, (nw, nh), interpolation=cv2.INTER_NEAREST)
    fgm = cv2.resize(fgm.astype(np.uint8), (nw, nh), interpolation=cv2.INTER_NEAREST) > 0
    if cfg.mask_background:
        lab[~fgm] = -1
    if cfg.rotation_deg > 0:
        img, lab, fgm = _rotate(img, lab, fgm, rng.uniform(-cfg.rotation_deg, cfg.rotation_deg))
    ch, cw = cfg.crop
    ph, pw = max(0, ch - nh), max(0, cw - nw)
    if ph or pw:
        img = np.pad(img, ((0, ph), (0, pw), (0, 0)))
        lab = np.pad(lab, ((0, ph), (0, pw)), constant_values=-1)
        fgm = np.pad(fgm, ((0, ph), (0, pw)))
    y0 = int(rng.integers(0, img.shape[0] - ch + 1))
    x0 = int(rng.integers(0, img.shape[1] - cw + 1))
    img, lab, fgm = img[y0:y0 + ch, x0:x0 + cw], lab[y0:y0 + ch, x0:x0 + cw], fgm[y0:y0 + ch, x0:x0 + cw]
    if cfg.flip and rng.random() < 0.5:
        img, lab, fgm = img[:, ::-1], lab[:, ::-1], fgm[:, ::-1]
        if img.shape[2] > 3:
            img = img.copy()
            img[..., NORMAL_X] *= -1
    img = np.ascontiguousarray(img)
    img = _jitter(img, cfg, rng) if img.shape[2] == 3 else np.concatenate([_jitter(img[..., :3], cfg, rng),
                                                                           img[..., 3:]], -1)
    if cfg.mask_background:
        img[~fgm] = fill
    lab = lab.astype(np.int64)
    ids, counts = np.unique(lab[lab >= 0], return_counts=True)
    small = ids[counts < cfg.min_segment_px]
    if len(small):
        lab[np.isin(lab, small)] = -1
    return np.ascontiguousarray(img.transpose(2, 0, 1)), lab


def make_batch(source: LabelSource, cfg: TrainConfig, step: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The batch of ``step``: a pure function of (seed, step) → (B×C×h×w float, B×h×w long, B long group
    index of each image: :func:`batch_items`)."""
    rng = np.random.default_rng([cfg.seed, step])
    idx, groups = batch_items(source, cfg, rng)
    foreground = getattr(source, "foreground", None) if cfg.mask_background else None
    pairs = [augment(*source[int(i)], cfg, rng, None if foreground is None else foreground(int(i))) for i in idx]
    return (torch.from_numpy(np.stack([p[0] for p in pairs])), torch.from_numpy(np.stack([p[1] for p in pairs])),
            torch.from_numpy(groups))


Batch = tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # what make_batch returns


def prefetch_threads(device: torch.device) -> int:
    """Threads that make the next batches while ``device`` runs a step: none on the CPU (the cores train the
    network), else up to PREFETCH_THREADS, one core left to the loop that feeds the device."""
    return 0 if device.type == "cpu" else max(1, min(PREFETCH_THREADS, (os.cpu_count() or 2) - 1))


def training_batches(source: LabelSource, cfg: TrainConfig, steps: range, threads: int = 0) -> Iterator[Batch]:
    """:func:`make_batch` of each step of ``steps``, in order. With ``threads`` > 0 a thread pool makes them up to
    2 × threads steps ahead (augmentation overlaps the device's work); a batch is a pure function of (seed, step),
    so the batches are the same either way."""
    if threads <= 0:
        for step in steps:
            yield make_batch(source, cfg, step)
        return
    pool = ThreadPoolExecutor(threads, thread_name_prefix="batches")
    try:
        todo, pending = iter(steps), deque()
        for step in todo:
            pending.append(pool.submit(make_batch, source, cfg, step))
            if len(pending) == 2 * threads:
                break
        while pending:
            batch = pending.popleft().result()
            step = next(todo, None)
            if step is not None:
                pending.append(pool.submit(make_batch, source, cfg, step))
            yield batch
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def step_loss(net: EmbeddingNet, source: LabelSource, cfg: TrainConfig, step: int, device: torch.device,
              batch: Batch | None = None) -> torch.Tensor:
    """Forward pass and contrastive loss of training step ``step`` (deterministic in (seed, step)); ``batch``:
    that step's :func:`make_batch`, if already made."""
    rgb, labels, groups = make_batch(source, cfg, step) if batch is None else batch
    rgb = cfg.layout(rgb.to(device))
    with cfg.autocast(device):
        emb = net(rgb)
    pixel_rng = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)
    return prototype_contrastive_loss(emb, labels.to(device), cfg.tau, cfg.loss_pixels, pixel_rng,
                                      cfg.negatives, groups.to(device) if cfg.negatives == "video" else None)


def new_embedding_net(net_cfg: NetConfig, cfg: TrainConfig, device: torch.device) -> EmbeddingNet:
    """A freshly initialised network on ``device``, in the memory layout ``cfg`` trains it in."""
    return cfg.layout(EmbeddingNet(net_cfg).to(device))


def _train_key(cfg: TrainConfig, net_cfg: NetConfig) -> dict:
    return {"train": settings_key(to_dict(cfg)), "net": to_dict(net_cfg)}


def _save_torch(path: Path, obj: dict) -> None:
    buf = io.BytesIO()
    torch.save(obj, buf)
    atomic_write_bytes(path, buf.getvalue())


def _checkpoints(out_dir: Path) -> list[Path]:
    """The CHECKPOINT_PT files in ``out_dir``, oldest first."""
    return sorted(out_dir.glob(CHECKPOINT_PT.replace("{step:06d}", "*")))


def _latest_checkpoint(out_dir: Path) -> Path | None:
    found = _checkpoints(out_dir)
    return found[-1] if found else None


def drop_checkpoints(out_dir: Path) -> None:
    """Delete ``out_dir``'s checkpoints once its final weights are written: they only serve a resume, and a
    finished run is not retrained (a 12.7 MB φ checkpoint per fold on tiny)."""
    shutil.rmtree(out_dir / Path(CHECKPOINT_PT).parent, ignore_errors=True)


def _save_checkpoint(out_dir: Path, step: int, state: dict) -> None:
    """Save ``state`` as the checkpoint after ``step`` steps (CHECKPOINT_PT) and delete the older ones."""
    path = out_dir / CHECKPOINT_PT.format(step=step)
    path.parent.mkdir(parents=True, exist_ok=True)
    _save_torch(path, state)
    for old in _checkpoints(out_dir):
        if old != path:
            old.unlink()


def _write_log(out_dir: Path, key: dict, losses: list[float], seconds: float, images: int, device: torch.device) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    write_json(out_dir / TRAINING_LOG_JSON, {
        "config": key, "steps": len(losses), "loss": losses, "final_loss_mean10": float(np.mean(losses[-10:])),
        "seconds_this_session": round(seconds, 2), "images_per_s": round(images / max(seconds, 1e-9), 3),
        "device": str(device), "threads": torch.get_num_threads()})
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(losses, lw=0.6, alpha=0.5, label="loss")
    k = max(1, len(losses) // 50)
    ax.plot(np.arange(k - 1, len(losses)), np.convolve(losses, np.ones(k) / k, mode="valid"), lw=1.5,
            label=f"mean of {k}")
    ax.set_xlabel("step")
    ax.set_ylabel("contrastive loss")
    ax.legend()
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(out_dir / LOSS_CURVE_PNG, buf.getvalue())


def train_embedding(source: LabelSource, cfg: TrainConfig, net_cfg: NetConfig, out_dir: str | Path,
                    progress: bool = True) -> Path:
    """Train an :class:`EmbeddingNet` with the prototype contrastive loss; returns the weights path.

    Resumes from the latest checkpoint in ``out_dir`` if its settings match (else raises), and
    returns at once if ``weights.pt`` was already written with the same settings.
    """
    out_dir = Path(out_dir)
    key = _train_key(cfg, net_cfg)
    weights = out_dir / WEIGHTS
    if weights.is_file():
        if torch.load(weights, map_location="cpu", weights_only=True)["key_hash"] == hash_json(key):
            return weights
        raise ValueError(f"{weights}: trained with other settings; use another out_dir or delete it")
    if len(source) == 0:
        raise ValueError("the label source is empty")
    if getattr(source, "geometry", False) != net_cfg.geometry:
        raise ValueError(f"the network {'reads' if net_cfg.geometry else 'does not read'} geometry and the label "
                         f"source's frames {'carry' if getattr(source, 'geometry', False) else 'do not carry'} it: "
                         f"build the source with geometry={net_cfg.geometry}")
    if cfg.negatives == "global" and not getattr(source, "global_ids", False):
        raise ValueError("negatives 'global' needs a label source whose ids name the same object in every frame "
                         "(global_ids); this one numbers segments per scene: use 'image'")
    device = begin_training(cfg)
    net = new_embedding_net(net_cfg, cfg, device)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    start, losses = 0, []
    latest = _latest_checkpoint(out_dir)
    if latest is not None:
        state = torch.load(latest, map_location=device, weights_only=True)
        if state["key_hash"] != hash_json(key):
            raise ValueError(f"{latest}: checkpoint has other training settings; use another out_dir or delete it")
        net.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        start, losses = int(state["step"]), list(state["losses"])

    net.train()
    t0, images = time.perf_counter(), 0
    bar = tqdm(range(start, cfg.steps), initial=start, total=cfg.steps, disable=not progress, desc="train φ",
               dynamic_ncols=True)
    batches = training_batches(source, cfg, range(start, cfg.steps), prefetch_threads(device))
    try:
        for step, batch in zip(bar, batches):
            for g in opt.param_groups:
                g["lr"] = cfg.lr * (1 - step / cfg.steps) ** 0.9
            loss = step_loss(net, source, cfg, step, device, batch)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            losses.append(loss.item())
            if not np.isfinite(losses[-1]):
                raise FloatingPointError(f"training loss became {losses[-1]} at step {step}; lower lr "
                                         f"(now {cfg.lr}) or check the label source")
            images += cfg.batch_size
            bar.set_postfix(loss=f"{losses[-1]:.4f}")
            done = step + 1
            if done % cfg.checkpoint_every == 0 or done == cfg.steps:
                _save_checkpoint(out_dir, done, {"step": done, "model": net.state_dict(), "optimizer": opt.state_dict(),
                                                 "losses": losses, "key_hash": hash_json(key)})
                _write_log(out_dir, key, losses, time.perf_counter() - t0, images, device)
    finally:
        batches.close()  # its thread pool, at once (an error in a step too)
    bar.close()
    _save_torch(weights, {"net_cfg": to_dict(net_cfg), "state_dict": net.state_dict(), "key_hash": hash_json(key)})
    drop_checkpoints(out_dir)
    return weights


def at_output_stride(net_cfg: NetConfig, output_stride: int) -> NetConfig:
    """``net_cfg`` at ``output_stride`` (8 or 16) with weights of the same shapes: the dilated stages change and the
    ASPP rates scale by the trained stride ÷ ``output_stride``, as DeepLabV3 trains at 16 and segments at 8 with
    (6, 12, 18) → (12, 24, 36)."""
    if output_stride == net_cfg.output_stride:
        return net_cfg
    scale = net_cfg.output_stride / output_stride
    return replace(net_cfg, output_stride=output_stride, aspp_rates=tuple(int(r * scale) for r in net_cfg.aspp_rates))


def load_embedding_net(path: str | Path, device: str | torch.device = "cpu", output_stride: int = 0) -> EmbeddingNet:
    """Load ``weights.pt`` written by :func:`train_embedding` → network in eval mode on ``device``; at the output
    stride it trained at, or with ``output_stride`` (8 or 16) rebuilt at that one (:func:`at_output_stride`)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no trained weights (run the method's fit first)")
    state = torch.load(path, map_location="cpu", weights_only=True)
    net_cfg = from_dict(NetConfig, state["net_cfg"])
    net = EmbeddingNet(at_output_stride(net_cfg, output_stride) if output_stride else net_cfg)
    net.load_state_dict(state["state_dict"])
    return net.to(resolve_device(str(device))).eval()

