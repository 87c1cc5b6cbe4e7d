"""`ours-gt-merging`: a diagnostic ceiling of the matching step (not in the paper; it reads ground truth).

φ2 is trained, exactly as in `ours`, on pseudo-labels that a perfect matching and pruning step would
give: the LCCP + SymSeg over-segments of each training video with every segment-graph edge whose two
segments cover the same ground-truth instance merged (:func:`selfseg.eval.merges.merge_same_instance`).
A segment's instance is the majority GT instance of its projected pixels over the training frames
(0, background, when most of them fall off every object). Its gap to `ours-v2` is the most graph
matching can add on the dataset's over-segmentation; `ours` sits between the two.
"""
from __future__ import annotations

import numpy as np

from selfseg.dataset import LabeledVideo, Video
from selfseg.eval.merges import merge_same_instance, relabel, segment_instances
from selfseg.method.pipeline import (LABEL_MAP_PNG, SEGMAPS_DIR, SEGMENTS_NPZ, Ours, OursConfig, read_label_map)
from selfseg.method.segment_graph import SegmentGraph
from selfseg.method.train import FrameLabelSource


def segment_votes(segmaps: list[np.ndarray], insts: list[np.ndarray], n_segments: int) -> np.ndarray:
    """Majority GT instance (int64) of each of ``n_segments`` segments from frames' segment maps (int, −1 =
    none) and instance maps (0 = background): the instance most of its labelled pixels show; 0 if none."""
    return segment_instances(np.concatenate([m.ravel() for m in segmaps]),
                             np.concatenate([m.ravel() for m in insts]), n_segments)


class OursGTMerging(Ours):
    """φ2 trained on the over-segments merged by ground truth (see the module docstring)."""

    name = "ours-gt-merging"
    config_cls = OursConfig
    needs_ground_truth = True

    def label_source(self, train_videos: list[Video]):
        cache = self.run_overseg(train_videos)
        groups: dict[str, np.ndarray] = {}
        for v in train_videos:
            if not isinstance(v, LabeledVideo):
                raise TypeError(f"method {self.name!r} reads ground truth and needs LabeledVideo objects, "
                                f"got {type(v).__name__} for video {v.video_id}")
            seg_dir = cache.path("overseg", v.video_id)
            graph = SegmentGraph.load(seg_dir / SEGMENTS_NPZ)
            frames = self.training_frames(v)
            segmaps = [read_label_map(seg_dir / SEGMAPS_DIR / LABEL_MAP_PNG.format(frame_id=f)) for f in frames]
            insts = [v.inst(f).astype(np.int64) for f in frames]
            groups[v.video_id] = merge_same_instance(graph.edges, segment_votes(segmaps, insts, graph.n_segments))

        def load(video: Video, fid: int) -> np.ndarray:
            m = read_label_map(cache.path("overseg", video.video_id) / SEGMAPS_DIR / LABEL_MAP_PNG.format(frame_id=fid))
            return relabel(m, groups[video.video_id]).astype(np.int32)

        source = FrameLabelSource([(v, f, load) for v in train_videos for f in self.training_frames(v)],
                                  geometry=self.config.net.geometry)
        return source, {"gt_merging": [cache.key_hash("overseg", v.video_id) for v in train_videos],
                        "groups": {k: g.tolist() for k, g in groups.items()}}
