"""train + segment: the saved model segments exactly as the evaluated method; model folders are checked."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from selfseg.dataset import Dataset, read_inst
from selfseg.eval.cli import main as evaluate
from selfseg.eval.folds import fold_split, select_test_frames
from selfseg.method.background import BackgroundConfig, frame_foreground
from selfseg.method.cli import segment_main, train_main
from selfseg.method.deploy import MODEL_JSON, preview
from selfseg.writers import write_inst

ROOT = Path(__file__).resolve().parents[1]
TINY: Path  # the generated tiny preset (conftest's tiny_dataset), set for the module below


@pytest.fixture(autouse=True, scope="module")
def _tiny(tiny_dataset):
    global TINY
    TINY = tiny_dataset


# one torch thread for both trainings: a forked evaluate worker and this process may otherwise use
# different thread counts, and float reductions then differ in the last bits
SHORT = ["--config", str(ROOT / "configs/ours-tiny.yaml"), "--set", "phi1_train.steps=20", "--set", "train.steps=20",
         "--set", "phi1_train.threads=1", "--set", "train.threads=1"]


def _write_K(path: Path, K: np.ndarray) -> Path:
    path.write_text(" ".join(repr(float(v)) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])))
    return path


@pytest.mark.slow
def test_train_and_segment_reproduce_evaluate(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    ds = Dataset(TINY)
    stages = tmp_path / "stages"
    sets = SHORT + ["--set", f"stage_dir={stages}"]
    assert evaluate(["--method", "ours-v2", "--data", str(TINY), *sets, "--folds", "0", "--limit", "2",
                     "--out", str(tmp_path / "r"), "--quiet"]) == 0
    # `train` on the unlabeled view evaluate gave the method (same frames; recon and over-segments stay
    # cached, φ is trained again: training is deterministic)
    (view,) = (tmp_path / "r/work/_views").glob(f"*/{TINY.name}")
    shutil.rmtree(stages / "phi1")
    train_ids, test_ids = fold_split(ds, 0)
    model = tmp_path / "model"
    assert train_main(["--method", "ours-v2", "--data", str(view), *sets, "--videos", ",".join(train_ids),
                       "--out", str(model)]) == 0
    meta = json.loads((model / MODEL_JSON).read_text())
    assert meta["method"] == "ours-v2" and meta["training_data"]["videos"] == train_ids
    assert meta["training_data"]["content_hash"] == Dataset(view).content_hash() and (model / "weights.pt").is_file()
    pred_dir = tmp_path / "r/predictions/ours-v2/tiny"
    compared = 0
    for vid in test_ids:
        lv = ds.labeled(vid)
        for f in select_test_frames(lv.frame_ids, 10, 2):
            fg = tmp_path / f"fg_{vid}_{f}.png"
            write_inst(fg, (lv.inst(f) > 0).astype(np.uint16))
            out = tmp_path / f"seg_{vid}_{f}.png"
            assert segment_main(["--model", str(model), "--rgb", str(TINY / f"videos/{vid}/rgb/{f:06d}.png"),
                                 "--foreground", str(fg), "--out", str(out)]) == 0
            assert np.array_equal(read_inst(out), read_inst(pred_dir / f"{vid}/{f:06d}.png"))
            compared += 1
    assert compared == 4
    # folder mode with the estimated foreground, preview and fps
    v = ds.video(test_ids[0])
    rgb_dir, depth_dir = tmp_path / "in/rgb", tmp_path / "in/depth"
    for f in v.frame_ids[:3]:
        for sub, d in ((rgb_dir, "rgb"), (depth_dir, "depth")):
            sub.mkdir(parents=True, exist_ok=True)
            shutil.copy(TINY / f"videos/{v.video_id}/{d}/{f:06d}.png", sub / f"{f:06d}.png")
    K = _write_K(tmp_path / "K.txt", v.K())
    capsys.readouterr()
    assert segment_main(["--model", str(model), "--rgb", str(rgb_dir), "--depth", str(depth_dir), "--depth-scale",
                         "0.1", "--intrinsics", str(K), "--foreground", "plane", "--out", str(tmp_path / "segs"),
                         "--preview", "--quiet"]) == 0
    assert "3 frames in" in capsys.readouterr().out
    for f in v.frame_ids[:3]:
        seg = read_inst(tmp_path / f"segs/{f:06d}.png")
        fg = frame_foreground(v.depth_m(f), v.K(), BackgroundConfig())
        assert seg.shape == (ds.height, ds.width) and seg.max() > 0
        assert not (seg[~fg] > 0).any()  # instances only inside the estimated foreground
        assert cv2.imread(str(tmp_path / f"segs/preview/{f:06d}.png")).shape == (ds.height, ds.width, 3)
    # the full method (matching, pseudo-labels, φ2) trains and segments from the same cached stages
    assert train_main(["--method", "ours", "--data", str(view), *sets, "--videos", ",".join(train_ids),
                       "--out", str(tmp_path / "ours")]) == 0
    out = tmp_path / "ours.png"
    assert segment_main(["--model", str(tmp_path / "ours"), "--rgb", str(rgb_dir / f"{v.frame_ids[0]:06d}.png"),
                         "--depth", str(depth_dir / f"{v.frame_ids[0]:06d}.png"), "--depth-scale", "0.1",
                         "--intrinsics", str(K), "--foreground", "plane", "--out", str(out), "--preview"]) == 0
    assert read_inst(out).max() > 0 and out.with_suffix(".preview.png").is_file()


def _err(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def _fake_model(path: Path, **meta) -> Path:
    path.mkdir(parents=True)
    (path / MODEL_JSON).write_text(json.dumps({"format": "selfseg-model", "model_version": 1, "method": "ours",
                                               **meta}))
    return path


def test_bad_models_and_inputs(tmp_path, capsys):
    rgb = TINY / "videos/000000/rgb/000000.png"
    args = ["--rgb", str(rgb), "--out", str(tmp_path / "o.png")]
    assert segment_main(["--model", str(tmp_path / "nothing"), *args]) == 2
    assert "model.json: missing" in _err(capsys)
    assert segment_main(["--model", str(_fake_model(tmp_path / "v9", model_version=9)), *args]) == 2
    assert "version 9" in _err(capsys)
    assert segment_main(["--model", str(_fake_model(tmp_path / "sup", method="supervised")), *args]) == 2
    assert "method 'supervised' cannot segment here" in _err(capsys)
    assert segment_main(["--model", str(_fake_model(tmp_path / "cfg")), *args]) == 2
    assert "config.json" in _err(capsys)
    assert train_main(["--method", "depth-clustering", "--data", str(TINY), "--out", str(tmp_path / "m")]) == 2
    assert "train/segment support the unlabeled embedding methods" in _err(capsys)
    assert train_main(["--method", "ours", "--data", str(TINY), "--videos", "999", "--out", str(tmp_path / "m")]) == 2
    assert "no video '999'" in _err(capsys)
    assert not (tmp_path / "o.png").exists() and not (tmp_path / "m").exists()


def test_bad_model_files_are_one_line(tmp_path, capsys):
    """A model.json that is not an object, and weights.pt that is empty, an image, text or another pickle: one
    line naming the file, exit 2 (torch.load with weights_only: nothing in the file is executed)."""
    import torch

    from selfseg.config import config_hash, to_dict
    from selfseg.method.deploy import CONFIG_JSON, WEIGHTS_PT
    from selfseg.method.pipeline import OursConfig

    rgb = TINY / "videos/000000/rgb/000000.png"
    args = ["--rgb", str(rgb), "--out", str(tmp_path / "o.png")]
    listed = tmp_path / "list"
    listed.mkdir()
    (listed / MODEL_JSON).write_text("[1, 2]")
    assert segment_main(["--model", str(listed), *args]) == 2
    assert _err(capsys).strip() == f"segment: error: {listed / MODEL_JSON}: expected a JSON object, got a list"
    cases = {"empty": b"", "png": rgb.read_bytes(), "text": b"not weights\n"}
    for name, data in cases.items():
        model = _fake_model(tmp_path / name, config_hash=config_hash(OursConfig()))
        (model / CONFIG_JSON).write_text(json.dumps(to_dict(OursConfig())))
        (model / WEIGHTS_PT).write_bytes(data)
        assert segment_main(["--model", str(model), *args]) == 2, name
        err = _err(capsys)
        assert len(err.strip().splitlines()) == 1 and f"{model / WEIGHTS_PT}: not a weights file" in err, err
    other = _fake_model(tmp_path / "other", config_hash=config_hash(OursConfig()))
    (other / CONFIG_JSON).write_text(json.dumps(to_dict(OursConfig())))
    torch.save({"something": [1, 2]}, other / WEIGHTS_PT)
    assert segment_main(["--model", str(other), *args]) == 2
    err = _err(capsys)
    assert len(err.strip().splitlines()) == 1 and f"{other / WEIGHTS_PT}: weights do not fit" in err, err
    assert not (tmp_path / "o.png").exists()


def test_plane_foreground_and_preview_on_a_tiny_frame():
    ds = Dataset(TINY)
    lv = ds.labeled(ds.video_ids[0])
    f = lv.frame_ids[0]
    gt = lv.inst(f) > 0
    fg = frame_foreground(lv.depth_m(f), lv.K(), BackgroundConfig())
    iou = (fg & gt).sum() / (fg | gt).sum()
    assert iou > 0.6, iou  # the table is removed, the objects stay
    inst = lv.inst(f)
    p = preview(lv.rgb(f), inst)
    assert p.shape == lv.rgb(f).shape and np.array_equal(p[inst == 0], lv.rgb(f)[inst == 0])


def test_evaluate_with_plane_foreground_gives_methods_the_estimated_mask(tmp_path):
    from selfseg.eval.protocol import estimated_foreground

    out = tmp_path / "r"
    assert evaluate(["--method", "one-segment", "--data", str(TINY), "--foreground", "plane", "--folds", "0",
                     "--limit", "1", "--out", str(out), "--quiet"]) == 0
    rec = json.loads((out / "scores/tiny/one-segment@fg-plane/fold0.json").read_text())
    assert rec["options"]["foreground"] == "plane" and rec["name"] == "one-segment@fg-plane"
    ds = Dataset(TINY)
    for vid in rec["test_videos"]:
        lv = ds.labeled(vid)
        pred = read_inst(out / f"predictions/one-segment@fg-plane/tiny/{vid}/000000.png")
        est = estimated_foreground(lv, 0)
        assert np.array_equal(pred > 0, est) and not np.array_equal(est, lv.inst(0) > 0)
    # scored against the ground truth: missed foreground lowers recall below the GT-foreground run's
    assert evaluate(["--method", "one-segment", "--data", str(TINY), "--folds", "0", "--limit", "1",
                     "--out", str(out), "--quiet"]) == 0
    gt = json.loads((out / "scores/tiny/one-segment/fold0.json").read_text())
    assert rec["metrics"]["R"] < gt["metrics"]["R"]
