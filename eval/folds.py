"""The protocol's folds and test frames: 3-fold cross-validation over videos, every 10th frame of a held-out video,
and the options a run is made with (:class:`EvalOptions`, recorded in every result)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selfseg.dataset import DATASET_INFO, Dataset, DatasetError
from selfseg.eval.aggregate import BOOTSTRAP_SEED, N_BOOTSTRAP
from selfseg.eval.layout import N_FOLDS


@dataclass
class EvalOptions:
    """Protocol options; all are recorded in every result file."""

    folds: tuple[int, ...] = (0, 1, 2)
    frame_stride: int = 10  # test frames: every frame_stride-th frame of a held-out video, from frame 0
    limit: int | None = None  # at most this many test frames per held-out video (quick runs)
    name: str | None = None  # result name (default: the method name), for variants and external runs
    poses_given: bool = False  # give methods the ground-truth camera poses (ablation)
    # Foreground given to methods: "gt" (the paper's protocol) or "plane" (estimated from each frame's depth
    # by removing the support plane, as a robot would; scoring still uses the ground-truth foreground)
    foreground: str = "gt"
    n_boot: int = N_BOOTSTRAP
    seed: int = BOOTSTRAP_SEED  # bootstrap seed
    # a user's method (``package.module:Class``) is given its training videos' labels (never the test videos')
    method_needs_ground_truth: bool = False

    def __post_init__(self):
        if self.frame_stride < 1:
            raise ValueError(f"frame_stride must be ≥ 1, got {self.frame_stride}")
        if self.limit is not None and self.limit < 1:
            raise ValueError(f"limit must be ≥ 1, got {self.limit}")
        if self.foreground not in ("gt", "plane"):
            raise ValueError(f"foreground must be 'gt' or 'plane', got {self.foreground!r}")
        bad = [k for k in self.folds if not 0 <= k < N_FOLDS]
        if bad or not self.folds:
            raise ValueError(f"folds must be a non-empty subset of 0..{N_FOLDS - 1}, got {list(self.folds)}")


def make_folds(dataset: Dataset, n_folds: int = N_FOLDS) -> list[list[str]]:
    """Test videos of each fold: ``dataset_info.json['folds']`` if stored, else a permutation
    seeded by the dataset's seed, split into ``n_folds`` near-equal parts (each list sorted)."""
    stored = dataset.info.get("folds")
    if stored is not None:
        folds = [sorted(str(v) for v in f) for f in stored]
        flat = [v for f in folds for v in f]
        if len(folds) != n_folds or sorted(flat) != dataset.video_ids:
            raise DatasetError(f"{dataset.root / DATASET_INFO}: 'folds' must split the {len(dataset.video_ids)} "
                               f"videos into {n_folds} disjoint lists")
        return folds
    if len(dataset.video_ids) < n_folds:
        raise DatasetError(f"{dataset.root}: {n_folds}-fold cross-validation needs at least {n_folds} videos, "
                           f"found {len(dataset.video_ids)}")
    order = np.random.default_rng(dataset.seed).permutation(len(dataset.video_ids))
    return [sorted(dataset.video_ids[i] for i in part) for part in np.array_split(order, n_folds)]


def fold_split(dataset: Dataset, fold: int) -> tuple[list[str], list[str]]:
    """(training video ids, test video ids) of a fold; the two never share a video."""
    test = make_folds(dataset)[fold]
    return [v for v in dataset.video_ids if v not in test], test


def select_test_frames(frame_ids: list[int], stride: int, limit: int | None) -> list[int]:
    """Every ``stride``-th frame (from the first), at most ``limit`` of them."""
    return list(frame_ids[::stride][:limit])
