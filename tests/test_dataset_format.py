"""The dataset format module: round trips, bad input, and the ground-truth guard."""
import json

import numpy as np
import pytest

from selfseg import dataset as ds
from selfseg import guard, poses, writers
from selfseg.config import ConfigError, config_hash, load_config


def test_depth_roundtrip_quantisation(tmp_path):
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.2, 3.0, (12, 16)).astype(np.float32)
    depth[0, 0] = 0.0
    p = tmp_path / "d.png"
    writers.write_depth_m(p, depth)
    back = ds.read_depth_m(p, ds.DEPTH_SCALE_MM)
    assert back[0, 0] == 0
    assert np.max(np.abs(back - depth)) <= ds.DEPTH_SCALE_MM / 1000 / 2 + 1e-6  # half a quantisation step
    again = tmp_path / "d2.png"
    writers.write_depth_m(again, back)
    assert np.array_equal(ds.read_depth_m(again, ds.DEPTH_SCALE_MM), back)  # exact after one round


def test_nan_depth_refused(tmp_path):
    d = np.ones((4, 4), np.float32)
    d[1, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        writers.write_depth_m(tmp_path / "d.png", d)
    assert not (tmp_path / "d.png").exists()


def test_rgb_and_inst_roundtrip(tmp_path):
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (8, 10, 3), dtype=np.uint8)
    inst = rng.integers(0, 70000 // 2, (8, 10)).astype(np.uint16)
    writers.write_rgb(tmp_path / "c.png", rgb)
    writers.write_inst(tmp_path / "i.png", inst)
    assert np.array_equal(ds.read_rgb(tmp_path / "c.png"), rgb)
    assert np.array_equal(ds.read_inst(tmp_path / "i.png"), inst)


def test_pose_roundtrip():
    from selfseg.raycast import look_at
    T = look_at([0.3, -0.2, 0.5], [0, 0, 0])
    R, t = poses.T_to_rt(T)
    assert np.allclose(poses.rt_to_T(R, t), T)
    assert np.allclose(poses.invert_T(T) @ T, np.eye(4))


def test_dataset_reader(analytic_dataset):
    d = ds.Dataset(analytic_dataset)
    assert d.video_ids == ["000000", "000001", "000002"]
    v = d.video("000000")
    assert len(v) == 6 and v.rgb(0).shape == (120, 160, 3)
    assert v.depth_m(0).dtype == np.float32 and 0.3 < np.median(v.depth_m(0)[v.depth_m(0) > 0]) < 1.2
    with pytest.raises(ds.PosesNotGiven):
        v.T_world_cam(0)
    assert not hasattr(v, "inst")
    lv = d.labeled("000000")
    assert set(np.unique(lv.inst(0))) <= {0, 1, 2}
    assert lv.T_world_cam(3).shape == (4, 4)
    assert d.content_hash() == ds.Dataset(analytic_dataset).content_hash()


def test_ground_truth_guard(analytic_dataset):
    d = ds.Dataset(analytic_dataset)
    lv = d.labeled("000001")
    with guard.ground_truth_forbidden(analytic_dataset):
        d.video("000001").rgb(0)  # allowed
        with pytest.raises(guard.GroundTruthAccessError, match="mask_inst"):
            lv.inst(0)
        with pytest.raises(guard.GroundTruthAccessError):
            open(analytic_dataset / "videos/000001/scene_gt.json").read()
        import cv2
        with pytest.raises(guard.GroundTruthAccessError):
            cv2.imread(str(analytic_dataset / "videos/000001/mask_inst/000000.png"), cv2.IMREAD_UNCHANGED)
        assert cv2.imread(str(analytic_dataset / "videos/000001/rgb/000000.png")) is not None
    assert lv.inst(0).shape == (120, 160)  # allowed again outside the block


def test_bad_inputs_name_the_file(analytic_dataset, tmp_path):
    import shutil
    root = tmp_path / "copy"
    shutil.copytree(analytic_dataset, root)
    (root / "videos/000000/rgb/000002.png").write_bytes(b"not a png")
    (root / "videos/000000/depth/000003.png").unlink()
    v = ds.Dataset(root).video("000000")
    with pytest.raises(ds.DatasetError, match=r"rgb/000002.png: corrupt"):
        v.rgb(2)
    with pytest.raises(ds.DatasetError, match=r"depth/000003.png: missing"):
        v.depth_m(3)
    cam = json.loads((root / "videos/000001/scene_camera.json").read_text())
    cam["0"]["cam_K"][0] = -5.0
    (root / "videos/000001/scene_camera.json").write_text(json.dumps(cam))
    with pytest.raises(ds.DatasetError, match=r"scene_camera.json frame 0: wrong intrinsics"):
        ds.Dataset(root).video("000001")
    with pytest.raises(ds.DatasetError, match="not a selfseg dataset"):
        ds.Dataset(tmp_path)
    empty = tmp_path / "empty"
    (empty / "videos").mkdir(parents=True)
    writers.write_dataset_info(empty, {"resolution": [4, 4]})
    with pytest.raises(ds.DatasetError, match="no videos"):
        ds.Dataset(empty)


def test_config_loading(tmp_path):
    from dataclasses import dataclass, field

    @dataclass
    class Inner:
        voxel_m: float = 0.005
        mode: str = "a"

    @dataclass
    class Outer:
        inner: Inner = field(default_factory=Inner)
        steps: int = 3

    cfg = load_config(Outer, overrides=["inner.voxel_m=0.01", "steps=5"])
    assert cfg.inner.voxel_m == 0.01 and cfg.steps == 5
    assert config_hash(cfg) != config_hash(Outer())
    with pytest.raises(ConfigError, match="did you mean 'voxel_m'"):
        load_config(Outer, overrides=["inner.voxel=0.01"])
    with pytest.raises(ConfigError, match="expected an integer"):
        load_config(Outer, overrides=["steps=abc"])
    # YAML 1.1 reads an exponent without a dot as a string; a number field takes it
    assert load_config(Outer, overrides=["inner.voxel_m=1e-3"]).inner.voxel_m == 0.001
    with pytest.raises(ConfigError, match="expected a number"):
        load_config(Outer, overrides=["inner.voxel_m=1e-3m"])
    y = tmp_path / "c.yaml"
    y.write_text("inner:\n  mode: b\n  bogus: 1\n")
    with pytest.raises(ConfigError, match=r"c.yaml: unknown config key 'inner.bogus'"):
        load_config(Outer, y)
