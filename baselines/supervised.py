"""Baselines A (`supervised`, the upper bound) and V1 (`v1-disjoint`): the embedding network trained
on ground-truth instance maps, with the same clustering as ours.

`supervised` trains on the training videos' own instance maps. `v1-disjoint` trains on a different
dataset (``train_data``, generated with a disjoint object subset) and never sees the test
dataset's labels, replacing the paper's COCO-trained V1 features.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from selfseg.dataset import Dataset, DatasetError, LabeledVideo, Video
from selfseg.method.embed_method import EmbeddingMethodBase, EmbeddingMethodConfig, video_key
from selfseg.method.train import FrameLabelSource


def gt_labels(video: LabeledVideo, frame_id: int) -> np.ndarray:
    """Ground-truth instance map → training labels (int32, background −1, instance k → k − 1)."""
    return video.inst(frame_id).astype(np.int32) - 1


def gt_label_source(method: EmbeddingMethodBase, videos: list[LabeledVideo]) -> tuple[FrameLabelSource, list]:
    for v in videos:
        if not isinstance(v, LabeledVideo):
            raise TypeError(f"method {method.name!r} trains on ground truth and needs LabeledVideo objects, "
                            f"got {type(v).__name__} for video {v.video_id}")
    items = [(v, f, gt_labels) for v in videos for f in method.training_frames(v)]
    return FrameLabelSource(items), [video_key(v) for v in videos]


class SupervisedMethod(EmbeddingMethodBase):
    """Baseline A: trained on the training videos' ground-truth instance maps."""

    name = "supervised"
    needs_ground_truth = True

    def label_source(self, train_videos: list[Video]) -> tuple[FrameLabelSource, list]:
        return gt_label_source(self, train_videos)


@dataclass
class V1DisjointConfig(EmbeddingMethodConfig):
    train_data: str = ""  # dataset folder generated with an object set disjoint from the test data


class V1DisjointMethod(EmbeddingMethodBase):
    """V1: supervised on a disjoint object set; ignores the (unlabeled) training videos it is given."""

    name = "v1-disjoint"
    config_cls = V1DisjointConfig
    needs_ground_truth = False

    def label_source(self, train_videos: list[Video]) -> tuple[FrameLabelSource, list]:
        if not self.config.train_data:
            raise DatasetError("v1-disjoint needs train_data: the path of a dataset generated with a disjoint "
                               "object subset")
        try:  # absolute: the sandbox refuses ground-truth names on relative paths (as for sim_data's train_data)
            ds = Dataset(os.path.abspath(self.config.train_data))
        except DatasetError as e:
            raise DatasetError(f"v1-disjoint train_data is not usable: {e}") from None
        return gt_label_source(self, [ds.labeled(v) for v in ds.video_ids])
