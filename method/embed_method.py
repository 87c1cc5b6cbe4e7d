"""Shared adapter for methods that segment with a trained embedding network plus mean-shift.

``fit`` builds a label source (the subclass decides from what), trains the network into a folder
of ``workdir`` keyed by the settings and the training frames, and ``segment`` runs the network on
the frame and clusters the foreground pixels (:func:`selfseg.method.meanshift.cluster_frame`). On
the CPU the clustering is numpy's, frame by frame (the reference results); on a GPU the embeddings
stay on it, the mode finding runs there, and ``segment_video`` embeds and clusters ``GPU_BATCH``
frames at a time.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from selfseg.config import to_dict
from selfseg.dataset import Video, video_content_hash
from selfseg.fileio import hash_json
from selfseg.method.features import embed_frames, foreground_box, video_frame
from selfseg.method.meanshift import MeanShiftConfig, cluster_frame, cluster_frames
from selfseg.method.network import EmbeddingNet, NetConfig
from selfseg.method.train import LabelSource, TrainConfig, load_embedding_net, resolve_device, train_embedding
from selfseg.method_api import Method

NET_DIR = "net-{key_hash}"  # in the workdir: the network's training run (files: selfseg.method.train)
GPU_BATCH = 16  # frames per network + clustering batch in segment_video, off the CPU


@dataclass
class EmbeddingMethodConfig:
    """Network, training schedule and clustering of an embedding method."""

    # The narrower "fast" DeepLabV3+ reaches the paper's ~6 fps on 2 CPU cores (bench/bench_inference.py).
    net: NetConfig = field(default_factory=lambda: NetConfig.preset("fast"))
    train: TrainConfig = field(default_factory=TrainConfig)
    cluster: MeanShiftConfig = field(default_factory=MeanShiftConfig)
    frame_stride: int = 5  # training uses every n-th frame of each training video
    device: str = "auto"  # inference device ("auto" → cuda if available, else cpu)
    test_flip: bool = False  # inference: each frame's embeddings averaged with its mirror image's (features.forward)
    # inference with train.fg_crop and mask_background: each foreground box grown to a square (masked background
    # beyond it, same scale), so every frame is one input shape: frames batched, a CUDA graph on a GPU
    test_square_crop: bool = False
    # inference at another output stride than the network trained at (8 or 16; 0: the same), with the same weights
    # (train.at_output_stride): DeepLabV3 trains at 16 and segments at 8. The segmenting network only, as test_flip.
    test_output_stride: int = 0

    def __post_init__(self):
        if self.frame_stride < 1:
            raise ValueError(f"frame_stride must be ≥ 1, got {self.frame_stride}")
        if self.test_output_stride not in (0, 8, 16):
            raise ValueError(f"test_output_stride must be 0 (as trained), 8 or 16, got {self.test_output_stride}")
        if self.test_square_crop and not (self.train.fg_crop and self.train.mask_background):
            raise ValueError("test_square_crop needs train.fg_crop and train.mask_background (the square's padding "
                             "is masked background)")


def video_key(video: Video) -> list:
    """Identity of a video's frames for cache keys: dataset folder, video id, frame ids, content."""
    return [os.path.abspath(video.root), video.video_id, video.frame_ids, video_content_hash(video)]


class EmbeddingMethodBase(Method):
    """Trained embedding network + vMF mean-shift. Subclasses implement :meth:`label_source`."""

    config_cls = EmbeddingMethodConfig
    needs_fit = True

    def __init__(self, config=None, workdir: str | Path | None = None):
        super().__init__(config, workdir)
        self.weights_path: Path | None = None
        self._net: EmbeddingNet | None = None
        self._device = resolve_device(self.config.device)

    def label_source(self, train_videos: list[Video]) -> tuple[LabelSource, Any]:
        """(training pairs, a JSON-able identity of what they were built from, for the cache key)."""
        raise NotImplementedError

    def training_frames(self, video: Video) -> list[int]:
        """The frames of ``video`` used for training (every ``frame_stride``-th)."""
        return video.frame_ids[::self.config.frame_stride]

    def fit(self, train_videos: list[Video]) -> None:
        if self.workdir is None:
            raise ValueError(f"method {self.name!r} needs a workdir to store its trained network")
        source, identity = self.label_source(train_videos)
        key = {"method": self.name, "net": to_dict(self.config.net), "train": to_dict(self.config.train),
               "frame_stride": self.config.frame_stride, "data": identity}
        out_dir = self.workdir / NET_DIR.format(key_hash=hash_json(key))
        self.load(train_embedding(source, self.config.train, self.config.net, out_dir))

    def load(self, weights_path: str | Path) -> None:
        """Use the network saved at ``weights_path`` (written by :func:`train_embedding`)."""
        self._net = load_embedding_net(weights_path, self._device, self.config.test_output_stride)
        self.weights_path = Path(weights_path)

    def embed(self, frame: np.ndarray, fg_mask: np.ndarray | None = None) -> np.ndarray:
        """Input frame (uint8 H×W×3 RGB, or with ``net.geometry`` :func:`~selfseg.method.features.input_frame`'s) →
        float32 D×H×W unit embeddings (the network runs at the training scale; with
        ``train.fg_crop``, inside the foreground box of ``fg_mask`` and zero outside it; with
        ``train.mask_background``, on the frame with everything outside ``fg_mask`` masked out; with ``test_flip``,
        averaged with the mirror image's embeddings)."""
        return self._embed([frame], None if fg_mask is None else [fg_mask])[0].cpu().numpy()

    def _embed(self, frames: list[np.ndarray], fg_masks: list[np.ndarray] | None) -> torch.Tensor:
        """B×D×H×W float32 embeddings of same-size frames, on the method's device (as :meth:`embed`)."""
        if self._net is None:
            raise RuntimeError(f"method {self.name!r} has no trained network: call fit() or load() first")
        train = self.network_train_config()
        boxes = None if train.crop_margin is None or fg_masks is None else \
            [foreground_box(m, train.crop_margin) for m in fg_masks]
        masks = fg_masks if train.mask_background else None
        return embed_frames(self._net, frames, self._device, train.image_size, boxes, masks,
                            self.config.test_flip, self.config.test_square_crop).float()

    def network_train_config(self) -> TrainConfig:
        """The training settings of the network that segments (its scale and foreground crop)."""
        return self.config.train

    def segment(self, video: Video, frame_id: int, fg_mask: np.ndarray) -> np.ndarray:
        return self.segment_frame(video_frame(video, frame_id, self.config.net.geometry), fg_mask)

    def segment_frame(self, frame: np.ndarray, fg_mask: np.ndarray) -> np.ndarray:
        """int32 H×W instance map of an input frame (as :meth:`embed` takes; 0 = background): embeddings, then the
        clustering on the method's device (numpy on the CPU)."""
        emb = self._embed([frame], [fg_mask])[0]
        return cluster_frame(emb.cpu().numpy() if self._device.type == "cpu" else emb, fg_mask, self.config.cluster)

    def segment_video(self, video: Video, frame_ids: list[int],
                      fg_masks: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """As :meth:`segment` per frame; off the CPU, ``GPU_BATCH`` frames share one network and clustering batch."""
        if self._device.type == "cpu":
            return super().segment_video(video, frame_ids, fg_masks)
        out = {}
        for start in range(0, len(frame_ids), GPU_BATCH):
            fids = frame_ids[start:start + GPU_BATCH]
            masks = [fg_masks[f] for f in fids]
            embs = self._embed([video_frame(video, f, self.config.net.geometry) for f in fids], masks)
            out.update(zip(fids, cluster_frames(embs, masks, self.config.cluster)))
        return out
