"""The interface every segmentation method implements: ours, the baselines and a user's own.

A method is built from its typed config dataclass, optionally ``fit`` on training videos, then
asked to segment test frames. Methods receive :class:`selfseg.dataset.Video` objects, which
carry RGB, depth, intrinsics and (only in the given-pose ablation) camera poses, but no ground
truth. The evaluator runs ``fit`` and ``segment`` in a separate process, on an unlabeled view of
the dataset (hard links of the frames, poses stripped unless given), with a ground-truth guard in
every thread (:mod:`selfseg.eval.protocol`). Only methods that declare ``needs_ground_truth = True``
(the supervised upper bound, the oracle) get :class:`selfseg.dataset.LabeledVideo` objects instead.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import ClassVar

import numpy as np

from selfseg.dataset import Video


@dataclasses.dataclass
class NoConfig:
    """For methods without settings."""


class Method:
    """Base class of segmentation methods.

    ``segment`` returns an integer H×W instance map: 0 = not an object, other ids arbitrary;
    only pixels inside ``fg_mask`` are scored.
    """

    name: ClassVar[str] = "method"
    config_cls: ClassVar[type] = NoConfig
    needs_ground_truth: ClassVar[bool] = False  # True: fit/segment get LabeledVideo objects
    needs_fit: ClassVar[bool] = False
    # A folder shared by every run and fold on the same outputs, where a method may cache per-video work (e.g.
    # reconstructions). The harness passes it in before ``fit`` (``evaluate``: OUT/work/_stages); None: use workdir.
    stage_root: Path | None = None

    def __init__(self, config=None, workdir: str | Path | None = None):
        self.config = config if config is not None else self.config_cls()
        self.workdir = Path(workdir) if workdir is not None else None  # where fit may cache files

    def fit(self, train_videos: list[Video]) -> None:
        """Learn from unlabeled training videos (default: nothing to learn)."""

    def segment(self, video: Video, frame_id: int, fg_mask: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def segment_video(self, video: Video, frame_ids: list[int], fg_masks: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Segment several frames of one video (override to share work across frames)."""
        return {f: self.segment(video, f, fg_masks[f]) for f in frame_ids}
