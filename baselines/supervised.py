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


def object_lookup(video: LabeledVideo) -> np.ndarray:
    """int32 table: instance id (0 = background) → training label of its global object (object id − 1;
    −1 for the background). Refuses a scene holding two instances of one object, which would share a
    label and so merge into one segment."""
    inst_to_obj = video.instance_to_object()
    objs = list(inst_to_obj.values())
    if len(set(objs)) != len(objs):
        twice = sorted({o for o in objs if objs.count(o) > 1})
        raise DatasetError(f"video {video.video_id}: object(s) {twice} appear as more than one instance; object ids "
                           f"cannot label them apart (use train.negatives other than 'global')")
    if min(objs, default=1) < 1:
        raise DatasetError(f"video {video.video_id}: object ids must be ≥ 1, got {min(objs)}")
    table = np.full(max(inst_to_obj, default=0) + 1, -1, np.int32)
    for inst, obj in inst_to_obj.items():
        table[inst] = obj - 1
    return table


def gt_object_labels(video: LabeledVideo, frame_id: int) -> np.ndarray:
    """Ground-truth instance map → global object labels (int32, background −1, object id o → o − 1): the
    same label for the same object in every video (``negatives: global``)."""
    inst = video.inst(frame_id)
    table = object_lookup(video)
    if inst.max(initial=0) >= len(table):
        raise DatasetError(f"video {video.video_id} frame {frame_id}: instance {int(inst.max())} is not in its "
                           f"scene_info instances")
    return table[inst]


def gt_label_source(method: EmbeddingMethodBase, videos: list[LabeledVideo]) -> tuple[FrameLabelSource, list]:
    """The training frames of ``videos`` with their ground-truth labels: per-scene instances, or global object
    ids when the method trains with ``negatives: global``."""
    for v in videos:
        if not isinstance(v, LabeledVideo):
            raise TypeError(f"method {method.name!r} trains on ground truth and needs LabeledVideo objects, "
                            f"got {type(v).__name__} for video {v.video_id}")
    global_ids = method.config.train.negatives == "global"
    if global_ids:
        for v in videos:
            object_lookup(v)  # refuse a scene with two instances of one object before training starts
    loader = gt_object_labels if global_ids else gt_labels
    items = [(v, f, loader) for v in videos for f in method.training_frames(v)]
    return FrameLabelSource(items, global_ids=global_ids, geometry=method.config.net.geometry), \
        [video_key(v) for v in videos]


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
