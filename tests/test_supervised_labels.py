"""The supervised bound's label source: per-scene instances, or global object ids with ``negatives: global``."""
import numpy as np
import pytest
import torch

from selfseg.analytic import box, make_dataset
from selfseg.baselines.supervised import gt_label_source, gt_labels, gt_object_labels
from selfseg.dataset import Dataset, DatasetError
from selfseg.method.embed_method import EmbeddingMethodConfig
from selfseg.method.meanshift import MeanShiftConfig
from selfseg.method.network import NetConfig
from selfseg.method.train import TrainConfig
from selfseg.registry import get_method_class

torch.set_num_threads(2)
TINY_NET = NetConfig(width=8, aspp_channels=16, low_level_channels=8, decoder_channels=16)


def method(negatives: str, tmp_path, **train):
    cfg = EmbeddingMethodConfig(net=TINY_NET, frame_stride=2, device="cpu",
                                cluster=MeanShiftConfig(min_component_px=20),
                                train=TrainConfig.preset("tiny", negatives=negatives, threads=2, image_size=96,
                                                         crop=(48, 64), **train))
    return get_method_class("supervised")(cfg, workdir=tmp_path)


def test_object_labels_are_the_same_for_an_object_in_every_video(analytic_dataset):
    """Scenes 0 and 1 hold object 1 as instance 1 and objects 2 / 3 as instance 2: object ids tell them
    apart (label = object id − 1), instance numbers do not."""
    ds = Dataset(analytic_dataset)
    seen = {}
    for vid in ds.video_ids:
        v = ds.labeled(vid)
        fid = v.frame_ids[0]
        inst, lab = v.inst(fid), gt_object_labels(v, fid)
        assert lab.dtype == np.int32 and np.all(lab[inst == 0] == -1)
        for i, o in v.instance_to_object().items():
            if (inst == i).any():
                assert np.all(lab[inst == i] == o - 1)
                seen.setdefault(o, set()).add(vid)
        assert np.array_equal(gt_labels(v, fid), inst.astype(np.int32) - 1)
    assert all(len(vids) >= 2 for vids in seen.values())  # every object is in two videos


def test_label_source_emits_object_ids_only_with_global_negatives(analytic_dataset, tmp_path):
    ds = Dataset(analytic_dataset)
    videos = [ds.labeled(v) for v in ds.video_ids]
    for negatives, loader in (("image", gt_labels), ("batch", gt_labels), ("global", gt_object_labels)):
        source, _ = gt_label_source(method(negatives, tmp_path), videos)
        assert source.global_ids == (negatives == "global")
        assert {item[2] for item in source.items} == {loader}
        v, f, _ = source.items[-1]
        assert np.array_equal(source[len(source) - 1][1], loader(v, f))


def test_two_instances_of_one_object_are_refused_with_global_ids(tmp_path):
    """They would share a label and train as one segment."""
    root = make_dataset(tmp_path / "twice", [[(box((0.06, 0.06, 0.06), (-0.08, 0, 0.03)), 4),
                                               (box((0.06, 0.06, 0.06), (0.08, 0, 0.03)), 4)]], n_frames=2)
    videos = [Dataset(root).labeled("000000")]
    with pytest.raises(DatasetError, match=r"000000: object\(s\) \[4\]"):
        gt_label_source(method("global", tmp_path), videos)
    source, _ = gt_label_source(method("image", tmp_path), videos)  # per-scene instances stay apart
    assert set(np.unique(source[0][1])) == {-1, 0, 1}


@pytest.mark.slow
def test_supervised_with_object_ids_and_masked_background_fits(analytic_dataset, tmp_path):
    """Global object ids and the masked background through fit and segment; segmenting never looks at the
    background (a frame with its table repainted gives the same segmentation)."""
    ds = Dataset(analytic_dataset)
    videos = [ds.labeled(v) for v in ds.video_ids]
    m = method("global", tmp_path, steps=30, mask_background=True)
    m.fit(videos)
    video, fid = videos[2], videos[2].frame_ids[-1]
    gt = video.inst(fid).astype(np.int64)
    fg = gt > 0
    pred = m.segment(video, fid, fg)
    assert pred.shape == gt.shape and np.all(pred[~fg] == 0) and len(np.unique(pred[fg])) >= 2
    rgb = video.rgb(fid)
    repainted = np.where(fg[..., None], rgb, np.uint8(30)).astype(np.uint8)
    assert np.array_equal(m.embed(rgb, fg), m.embed(repainted, fg))
