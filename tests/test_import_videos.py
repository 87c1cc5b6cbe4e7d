"""import_videos: round trips through the plain-folder and TUM layouts, a YCB-Video fixture, bad input."""
from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from selfseg.cli import main
from selfseg.dataset import Dataset
from selfseg.importers import associate, scale_K
from selfseg.manifest import verify
from selfseg.writers import depth_to_png_units

TINY: Path  # the generated tiny preset (conftest's tiny_dataset), set for the module below


@pytest.fixture(autouse=True, scope="module")
def _tiny(tiny_dataset):
    global TINY
    TINY = tiny_dataset


def _png(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), img)


def export_folder(video, out: Path, n: int, labels: bool = True) -> None:
    """The first n frames of a labelled tiny video in the plain-folder layout (depth units 0.1 mm)."""
    for f in video.frame_ids[:n]:
        _png(out / "rgb" / f"{f:06d}.png", video.rgb(f)[:, :, ::-1])
        _png(out / "depth" / f"{f:06d}.png", depth_to_png_units(video.depth_m(f), 0.1))
        if labels:
            _png(out / "mask_inst" / f"{f:06d}.png", video.inst(f))
    (out / "intrinsics.txt").write_text("\n".join(" ".join(repr(float(x)) for x in row) for row in video.K()))


def test_folder_round_trip_is_exact_and_resumes(tmp_path, capsys):
    ds = Dataset(TINY)
    src = tmp_path / "src"
    for vid in ds.video_ids[:2]:
        export_folder(ds.labeled(vid), src / vid, 4)
    out = tmp_path / "imported"
    assert main(["--format", "folder", str(src), "--out", str(out), "--depth-scale", "0.1", "--quiet"]) == 0
    back = Dataset(out)
    assert back.has_labels() and (back.width, back.height) == (ds.width, ds.height)
    for vid, new in zip(ds.video_ids[:2], back.video_ids):
        a, b = ds.labeled(vid), back.labeled(new)
        assert b.frame_ids == a.frame_ids[:4]
        np.testing.assert_allclose(b.K(), a.K(), atol=1e-9, rtol=0)
        for f in b.frame_ids:
            assert np.array_equal(b.rgb(f), a.rgb(f))
            assert np.array_equal(b.depth_m(f), a.depth_m(f))
            assert np.array_equal(b.inst(f), a.inst(f))
        assert set(b.instance_to_object()) == set(np.unique([a.inst(f) for f in b.frame_ids])) - {0}
    # resume: a removed video is re-imported, the other kept (not rewritten)
    kept = out / "videos" / "000000" / "scene_camera.json"
    mtime = kept.stat().st_mtime_ns
    shutil.rmtree(out / "videos" / "000001")
    assert main(["--format", "folder", str(src), "--out", str(out), "--depth-scale", "0.1", "--quiet"]) == 0
    stdout = capsys.readouterr().out
    assert "1 imported, 1 already present" in stdout
    assert kept.stat().st_mtime_ns == mtime and len(Dataset(out).video_ids) == 2
    assert verify(out) == (Dataset(out).content_hash(), []) and f"manifest hash {verify(out)[0]}" in stdout
    # other options into the same folder: refused
    assert main(["--format", "folder", str(src), "--out", str(out), "--depth-scale", "1", "--quiet"]) == 2


def test_folder_without_labels_subsampled_and_resized(tmp_path, capsys):
    ds = Dataset(TINY)
    a = ds.labeled(ds.video_ids[0])
    export_folder(a, tmp_path / "v", 6, labels=False)
    out = tmp_path / "o"
    assert main(["--format", "folder", str(tmp_path / "v"), "--out", str(out), "--depth-scale", "0.1",
                 "--frame-step", "2", "--resolution", "80x60", "--quiet"]) == 0
    back = Dataset(out)
    v = back.video(back.video_ids[0])
    assert not back.has_labels() and v.frame_ids == a.frame_ids[:6:2] and v.rgb(0).shape == (60, 80, 3)
    np.testing.assert_allclose(v.K(), scale_K(a.K(), 0.5, 0.5), atol=1e-9)
    assert v.K()[0, 2] == pytest.approx((a.K()[0, 2] + 0.5) / 2 - 0.5)
    from selfseg.eval.cli import main as evaluate

    assert evaluate(["--method", "one-segment", "--data", str(out), "--out", str(tmp_path / "r"), "--quiet"]) == 2
    assert "no ground truth" in capsys.readouterr().err


def test_tum_association_with_jittered_timestamps(tmp_path):
    ds = Dataset(TINY)
    a = ds.labeled(ds.video_ids[1])
    src = tmp_path / "tum"
    rng = np.random.default_rng(3)
    rgb_lines, depth_lines = ["# colour"], ["# depth"]
    n = 8
    for i, f in enumerate(a.frame_ids[:n]):
        t = 1000.0 + i / 15.0
        td = t + rng.uniform(-0.012, 0.012)
        _png(src / "rgb" / f"{t:.6f}.png", a.rgb(f)[:, :, ::-1])
        _png(src / "depth" / f"{td:.6f}.png", np.rint(a.depth_m(f) * 5000).astype(np.uint16))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{td:.6f} depth/{td:.6f}.png")
    depth_lines.append("2000.000000 depth/none.png")  # far from every colour frame: never used
    rng.shuffle(depth_lines[1:])
    (src / "rgb.txt").write_text("\n".join(rgb_lines))
    (src / "depth.txt").write_text("\n".join(depth_lines))
    (tmp_path / "K.txt").write_text(" ".join(repr(float(x)) for x in (a.K()[0, 0], a.K()[1, 1], a.K()[0, 2], a.K()[1, 2])))
    out = tmp_path / "o"
    assert main(["--format", "tum", str(src), "--out", str(out), "--intrinsics", str(tmp_path / "K.txt"), "--quiet"]) == 0
    v = Dataset(out).video("000000")
    assert len(v) == n
    for i, f in enumerate(a.frame_ids[:n]):
        assert np.array_equal(v.rgb(i), a.rgb(f))
        np.testing.assert_allclose(v.depth_m(i), np.rint(a.depth_m(f) * 5000) / 5000, atol=1e-6)
    np.testing.assert_allclose(v.K(), a.K(), atol=1e-9)


def test_associate_is_one_to_one_nearest_first():
    assert associate([0.0, 0.1, 0.2], [0.11, 0.09, 0.5], 0.02) == [(1, 0)] or associate(
        [0.0, 0.1, 0.2], [0.11, 0.09, 0.5], 0.02) == [(1, 1)]
    assert associate([0.0, 0.1], [0.015, 0.1], 0.02) == [(0, 0), (1, 1)]
    assert associate([0.0], [1.0], 0.02) == []


def make_ycb(root: Path, video, n: int, meta: bool = True) -> Path:
    from scipy.io import savemat

    d = root / "0048"
    for i, f in enumerate(video.frame_ids[:n]):
        _png(d / f"{i + 1:06d}-color.png", video.rgb(f)[:, :, ::-1])
        _png(d / f"{i + 1:06d}-depth.png", np.rint(video.depth_m(f) * 10000).astype(np.uint16))
        _png(d / f"{i + 1:06d}-label.png", video.inst(f).astype(np.uint8))
        ids = sorted(set(np.unique(video.inst(f)).tolist()) - {0})
        poses = np.zeros((3, 4, len(ids)))
        for k, o in enumerate(ids):
            poses[:, :, k] = np.hstack([np.eye(3), [[0.01 * o], [0.0], [0.5]]])
        if meta or i == 0:
            savemat(d / f"{i + 1:06d}-meta.mat", {"intrinsic_matrix": video.K(), "factor_depth": np.array([[10000.0]]),
                                                  "cls_indexes": np.array(ids, float).reshape(-1, 1), "poses": poses})
    return d


def test_ycb_video_fixture_imports_with_labels_and_poses(tmp_path):
    ds = Dataset(TINY)
    a = ds.labeled(ds.video_ids[2])
    make_ycb(tmp_path / "data", a, 3)
    out = tmp_path / "o"
    assert main(["--format", "ycb-video", str(tmp_path / "data"), "--out", str(out), "--quiet"]) == 0
    b = Dataset(out).labeled("000000")
    for i, f in enumerate(a.frame_ids[:3]):
        assert np.array_equal(b.inst(i), a.inst(f)) and np.array_equal(b.rgb(i), a.rgb(f))
        np.testing.assert_allclose(b.depth_m(i), np.rint(a.depth_m(f) * 10000) / 10000, atol=1e-6)
        gt = b.gt(i)
        assert sorted(g["inst_id"] for g in gt) == sorted(set(np.unique(a.inst(f)).tolist()) - {0})
        for g in gt:
            np.testing.assert_allclose(g["T_cam_model"][:3, 3], [0.01 * g["obj_id"], 0, 0.5], atol=1e-9)
    np.testing.assert_allclose(b.K(), a.K(), atol=1e-9)


def _err(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def test_bad_input_one_line_exit_2_nothing_written(tmp_path, capsys):
    ds = Dataset(TINY)
    a = ds.labeled(ds.video_ids[0])
    # missing -meta.mat
    make_ycb(tmp_path / "ycb", a, 2, meta=False)
    assert main(["--format", "ycb-video", str(tmp_path / "ycb"), "--out", str(tmp_path / "o1"), "--quiet"]) == 2
    assert "000002-meta.mat: missing" in _err(capsys) and not (tmp_path / "o1").exists()
    # TUM without associable depth
    t = tmp_path / "tum"
    _png(t / "rgb" / "a.png", a.rgb(0)[:, :, ::-1])
    _png(t / "depth" / "b.png", np.zeros((ds.height, ds.width), np.uint16))
    (t / "rgb.txt").write_text("1.0 rgb/a.png\n")
    (t / "depth.txt").write_text("1.5 depth/b.png\n")
    assert main(["--format", "tum", str(t), "--out", str(tmp_path / "o2"), "--camera", "freiburg1", "--quiet"]) == 2
    assert "depth.txt: no depth frame lies within 0.02 s" in _err(capsys) and not (tmp_path / "o2").exists()
    # intrinsics missing (TUM without --intrinsics/--camera; folder without intrinsics.txt)
    assert main(["--format", "tum", str(t), "--out", str(tmp_path / "o3"), "--quiet"]) == 2
    assert "intrinsics missing" in _err(capsys)
    f = tmp_path / "folder"
    export_folder(a, f, 2)
    (f / "intrinsics.txt").unlink()
    assert main(["--format", "folder", str(f), "--out", str(tmp_path / "o4"), "--quiet"]) == 2
    assert "intrinsics.txt: intrinsics file missing" in _err(capsys)
    export_folder(a, f, 2)
    # size mismatch between colour and depth, in the second frame: the video is not written
    _png(f / "depth" / "000001.png", np.zeros((10, 10), np.uint16))
    assert main(["--format", "folder", str(f), "--out", str(tmp_path / "o5"), "--depth-scale", "0.1", "--quiet"]) == 2
    assert "000001.png: depth is 10×10 but colour" in _err(capsys)
    assert not (tmp_path / "o5" / "videos" / "000000").exists()
    assert not list((tmp_path / "o5" / "videos").glob("*")) if (tmp_path / "o5" / "videos").exists() else True
    # depth of the wrong dtype (8-bit)
    _png(f / "depth" / "000001.png", np.zeros((ds.height, ds.width), np.uint8))
    assert main(["--format", "folder", str(f), "--out", str(tmp_path / "o6"), "--depth-scale", "0.1", "--quiet"]) == 2
    assert "000001.png: depth must be a single-channel uint16 PNG" in _err(capsys)


def test_unpaired_depth_or_label_frame_is_one_line_exit_2(tmp_path, capsys):
    """An extra depth or label frame without its colour frame is named, not silently dropped."""
    from scipy.io import savemat

    rgb, depth = np.zeros((6, 8, 3), np.uint8), np.full((6, 8), 5000, np.uint16)
    K = np.array([[8.0, 0, 3.5], [0, 8.0, 2.5], [0, 0, 1]])
    cases = []
    for name, extra in (("depth", "depth/000002.png"), ("mask_inst", "mask_inst/000002.png")):
        f = tmp_path / f"folder-{name}"
        for i in range(2):
            _png(f / "rgb" / f"{i:06d}.png", rgb)
            _png(f / "depth" / f"{i:06d}.png", depth)
            _png(f / "mask_inst" / f"{i:06d}.png", np.zeros((6, 8), np.uint16))
        _png(f / extra, depth)
        (f / "intrinsics.txt").write_text("8 8 3.5 2.5")
        cases.append(("folder", f, f / extra))
    for kind in ("depth", "label"):
        y = tmp_path / f"ycb-{kind}" / "0048"
        for i in (1, 2):
            _png(y / f"{i:06d}-color.png", rgb)
            _png(y / f"{i:06d}-depth.png", depth)
            savemat(y / f"{i:06d}-meta.mat", {"intrinsic_matrix": K, "factor_depth": np.array([[10000.0]])})
        _png(y / f"000003-{kind}.png", depth)
        cases.append(("ycb-video", y, y / f"000003-{kind}.png"))
    for k, (fmt, src, extra) in enumerate(cases):
        out = tmp_path / f"out{k}"
        assert main(["--format", fmt, str(src), "--out", str(out), "--quiet"]) == 2, (fmt, extra)
        err = _err(capsys)
        assert err.count(str(extra)) == 1 and "unpaired" in err, err
        assert not out.exists()
