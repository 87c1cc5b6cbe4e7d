"""End to end through the self-supervised pipeline (`ours`) on ray-cast scenes, no ground truth allowed."""
import numpy as np
import pytest

from selfseg.analytic import make_dataset, two_box_scenes
from selfseg.config import load_config
from selfseg.dataset import Dataset
from selfseg.guard import ground_truth_forbidden
from selfseg.baselines.gt_merging import OursGTMerging
from selfseg.method.pipeline import Ours, OursConfig, OursV2, OursV2Config, OursV3, OursV3Config, read_label_map

FAST = ["net.width=8", "net.aspp_channels=32", "net.decoder_channels=32", "net.low_level_channels=16",
        "train.steps=6", "train.batch_size=2", "train.crop=[64, 96]", "train.image_size=160",
        "phi1_train.steps=6", "phi1_train.batch_size=2", "phi1_train.crop=[64, 96]", "phi1_train.image_size=160",
        "frame_stride=4", "feature_stride=4", "pseudo.match.workers=1"]


@pytest.fixture(scope="module")
def dense_dataset(tmp_path_factory):
    """Three videos of 20 frames over 30° (1.5° per frame, dense enough to track)."""
    return make_dataset(tmp_path_factory.mktemp("dense"), two_box_scenes(), n_frames=20, width=160, height=120,
                        arc_deg=30)


def purity(label_map: np.ndarray, inst: np.ndarray) -> float:
    """Share of labelled object pixels whose label's majority ground-truth instance is their own."""
    keep = (label_map >= 0) & (inst > 0)
    good = 0
    for s in np.unique(label_map[keep]):
        gt = inst[keep & (label_map == s)]
        good += np.bincount(gt).max()
    return good / max(keep.sum(), 1)


@pytest.mark.slow
def test_ours_end_to_end_without_ground_truth(dense_dataset, tmp_path):
    ds = Dataset(dense_dataset)
    cfg = load_config(OursConfig, overrides=FAST)
    work = tmp_path / "work" / "ours" / "analytic" / "fold0"
    stage_root = tmp_path / "work" / "_stages"  # passed in by the harness, shared by every run and fold
    train = [ds.video(v) for v in ds.video_ids[:2]]
    with ground_truth_forbidden(dense_dataset):  # the whole self-supervised path runs under the guard
        method = Ours(cfg, work)
        method.stage_root = stage_root
        method.fit(train)
    labeled = ds.labeled("000002")
    fg = labeled.inst(0) > 0
    with ground_truth_forbidden(dense_dataset):
        pred = method.segment(ds.video("000002"), 0, fg)
    assert pred.shape == fg.shape and (pred[fg] > 0).all() and (pred[~fg] == 0).all()

    stages = method.stage_cache(train).root
    assert stages.parent == stage_root and stages.name.startswith(dense_dataset.name + "-")
    for vid in ds.video_ids[:2]:
        inst = ds.labeled(vid).inst(10)
        seg = read_label_map(stages / "overseg" / vid / "segmaps" / "000010.png")
        assert (seg >= 0).sum() > 0.8 * (inst > 0).sum()  # the projected segments cover the objects
        assert purity(seg, inst) > 0.9  # and each segment lies on one object
        pseudo = read_label_map(work / "pseudo" / "all" / "scenes" / "maps" / vid / "000010.png")
        assert purity(pseudo, inst) > 0.9
    assert (work / "pseudo" / "all" / "scenes" / "matches.json").is_file()

    # a re-run reuses every cached stage and network
    before = {p: p.stat().st_mtime_ns for p in stages.rglob("stage.json")}
    again = Ours(cfg, work)
    again.stage_root = stage_root
    with ground_truth_forbidden(dense_dataset):
        again.fit(train)
    assert len(before) == 4 and {p: p.stat().st_mtime_ns for p in stages.rglob("stage.json")} == before
    assert again.weights_path == method.weights_path

    # V2 shares the per-video stages and uses φ1 as its final network
    v2 = OursV2(load_config(OursV2Config, overrides=FAST), tmp_path / "work" / "ours-v2" / "analytic" / "fold0")
    v2.stage_root = stage_root
    with ground_truth_forbidden(dense_dataset):
        v2.fit(train)
    assert v2.weights_path.parent.parent.name == "phi1"  # φ1 from the shared cache, not retrained
    assert {p: p.stat().st_mtime_ns for p in stages.rglob("stage.json")} == before

    # V3 matches with the same φ1: it reads the φ1 segment features ours computed instead of embedding again
    feature_files = {p: p.stat().st_mtime_ns for p in v2.weights_path.parent.glob("features-*/*.npy")}
    assert sorted(p.stem for p in feature_files) == ds.video_ids[:2] and len({p.parent for p in feature_files}) == 1
    v3 = OursV3(load_config(OursV3Config, overrides=FAST), tmp_path / "work" / "ours-v3" / "analytic" / "fold0")
    v3.stage_root = stage_root
    with ground_truth_forbidden(dense_dataset):
        v3.label_source(train)
    assert {p: p.stat().st_mtime_ns for p in v2.weights_path.parent.glob("features-*/*.npy")} == feature_files
    for vid in ds.video_ids[:2]:
        ours_feats, v3_feats = (np.load(w / "pseudo" / "all" / "scenes" / "features" / f"{vid}.npy")
                                for w in (work, v3.workdir))
        assert np.array_equal(ours_feats, v3_feats)

    # the ground-truth merging ceiling (reads ground truth) reuses the same per-video stages; its labels are
    # the over-segments relabelled by their merged group, and it refuses videos without ground truth
    gtm = OursGTMerging(load_config(OursConfig, overrides=FAST), tmp_path / "work" / "ours-gt-merging")
    gtm.stage_root = stage_root
    with pytest.raises(TypeError, match="LabeledVideo"):
        gtm.label_source(train)
    source, identity = gtm.label_source([ds.labeled(v) for v in ds.video_ids[:2]])
    assert {p: p.stat().st_mtime_ns for p in stages.rglob("stage.json")} == before
    for i in range(0, len(source), 5):
        video, fid, _ = source.items[i]
        seg = read_label_map(stages / "overseg" / video.video_id / "segmaps" / f"{fid:06d}.png")
        _, lab = source[i]
        groups = np.asarray(identity["groups"][video.video_id])
        assert np.array_equal(lab, np.where(seg >= 0, groups[np.maximum(seg, 0)], -1))
        assert purity(lab, video.inst(fid)) > 0.9
