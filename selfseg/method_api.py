"""The interface every segmentation method implements: ours, the baselines and a user's own.

A method is built from its typed config dataclass, optionally ``fit`` on training videos, then
asked to segment test frames. Methods receive :class:`selfseg.dataset.Video` objects, which
carry RGB, depth, intrinsics and (only in the given-pose ablation) camera poses, but no ground
truth. The evaluator imports the method and runs ``fit`` and ``segment`` only in the method's own
sandboxed process, which holds an unlabeled view of the dataset (hard links of the frames, poses
stripped unless given) and nothing else of it (:mod:`selfseg.eval.sandbox`). Which labels a method is
given is the registry's to say (:data:`selfseg.registry.GROUND_TRUTH`: the supervised upper bound gets
its training videos' as :class:`selfseg.dataset.LabeledVideo` objects, the oracle every video's), or
``evaluate --method-needs-ground-truth`` for a user's method; never the class's.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import ClassVar

import numpy as np

from selfseg.dataset import Video


class BudgetExceededError(RuntimeError):
    """A method gave up because it passed a compute budget its config declares (e.g. matching's CPU seconds). The
    evaluator records the fold as failed under its budget, scores nothing of it and does not run it again
    (:mod:`selfseg.eval.protocol`); leaderboards show the failure."""


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
    # True: fit gets LabeledVideo objects where the caller hands labels out by class (train, benches); evaluate
    # ignores it and asks the registry (selfseg.registry.GROUND_TRUTH)
    needs_ground_truth: ClassVar[bool] = False
    needs_fit: ClassVar[bool] = False
    # A folder shared by every run and fold on the same outputs, where a method may cache per-video work (e.g.
    # reconstructions). The harness passes it in before ``fit`` (``evaluate``: OUT/work/_stages/<content>-<poses>
    # for a registered method, None for a user's); None: use workdir.
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
