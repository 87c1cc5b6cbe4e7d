"""Data statistics (``evaluate3d --stats``) on analytic fixtures with known answers."""
import numpy as np
import pytest

from selfseg.analytic import box, cylinder, make_dataset, two_box_scenes
from selfseg.config import load_config
from selfseg.dataset import Dataset
from selfseg.eval.cli import evaluate3d_main as main
from selfseg.eval.datastats import (breakdown_summary, format_stats, mesh_distances, object_breakdown,
                                    reconstruction_stats, sample_surface, touching_pairs, view_stats)
from selfseg.eval.table2 import STATS_JSON, run_stats, run_table2
from selfseg.fileio import read_json
from selfseg.method.pipeline import OursConfig
from selfseg.raycast import RaycastScene, look_at
from selfseg.writers import VideoWriter, write_dataset_info
from test_pipeline import FAST


def test_mesh_distances_and_touching_pairs():
    a = box((0.1, 0.1, 0.1), (0.0, 0.0, 0.05))
    b = box((0.1, 0.1, 0.1), (0.103, 0.0, 0.05))  # faces 3 mm apart
    c = cylinder(0.03, 0.1, (0.0, 0.2, 0.05))  # 12 cm from a's face (0.05 + 0.12 + 0.03 = 0.2)
    scene = RaycastScene.from_meshes([a, b, c], ids=[1, 2, 5])
    d = mesh_distances(scene)
    assert sorted(d) == [(1, 2), (1, 5), (2, 5)]
    assert d[(1, 2)] == pytest.approx(0.003, abs=1e-6)  # corners lie on the facing faces: exact
    assert d[(1, 5)] == pytest.approx(0.12, abs=2e-3)
    assert touching_pairs(scene) == [(1, 2)]
    assert touching_pairs(scene, max_dist_m=0.002) == []


def test_sample_surface_is_area_uniform_and_deterministic():
    m = box((0.1, 0.2, 0.05), (0, 0, 0))
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    pts = sample_surface(v, f, per_m2=1e5)
    assert np.array_equal(pts, sample_surface(v, f, per_m2=1e5))
    assert len(pts) == int(np.ceil(m.area * 1e5)) + len(v)
    top = np.isclose(pts[:-len(v), 2], 0.025)
    assert top.mean() == pytest.approx(0.1 * 0.2 / m.area, abs=0.01)  # share of the area on the top face


def test_object_breakdown_known_answer():
    # object 1: 6 points in segment 0, 2 in its own segment 1, 2 pruned
    # object 2: 8 points in segment 2, 2 in segment 0 (which is object 1's)
    # object 3: its one point in segment 0: no segment of its own, unmatched (Hungarian IoU: object 1 → segment 0
    # .46 beats object 1 → segment 1 .2 + object 3 → segment 0 .11)
    gt = np.array([1] * 10 + [2] * 10 + [3] + [0] * 3)
    pred = np.array([0] * 6 + [1] * 2 + [-1] * 2 + [2] * 8 + [0] * 2 + [0] + [2] * 3)
    out = object_breakdown(pred, gt)
    assert out[1] == {"points": 10, "own_segments": 2, "matched_segment": 0, "recall": 0.6, "pruned": 0.2,
                      "other": 0.0, "own_parts": 0.2}
    assert out[2] == {"points": 10, "own_segments": 1, "matched_segment": 2, "recall": 0.8, "pruned": 0.0,
                      "other": 0.2, "own_parts": 0.0}
    assert out[3] == {"points": 1, "own_segments": 0, "matched_segment": -1, "recall": 0.0, "pruned": 0.0,
                      "other": 1.0, "own_parts": 0.0}
    for o in out.values():  # the decomposition is complete
        assert o["recall"] + o["pruned"] + o["other"] + o["own_parts"] == pytest.approx(1.0)
    s = breakdown_summary(list(out.values()))
    assert s["objects"] == 3 and s["no_segment"] == 1 and s["split_share"] == pytest.approx(1 / 3)
    assert s["segments_per_object"] == pytest.approx(1.0) and s["recall"] == pytest.approx(1.4 / 3)
    assert s["lost_other"] == pytest.approx(1.2 / 3) and s["lost_pruned"] == pytest.approx(0.2 / 3)


def test_reconstruction_stats_known_answer():
    m = box((0.1, 0.1, 0.1), (0.0, 0.0, 0.05))
    scene = RaycastScene.from_meshes([m])
    g = np.linspace(-0.045, 0.045, 31)
    top = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    on = np.c_[top, np.full(len(top), 0.1)]  # 961 points on the top face (3 mm grid)
    off = on[:107] + [0, 0, 0.02]  # 107 points 2 cm above it: artifacts
    r = reconstruction_stats(np.vstack([on, off]), scene)
    assert r["points"] == 1068 and r["artifact_share"] == pytest.approx(107 / 1068)
    assert r["error_median_mm"] == pytest.approx(0.0, abs=1e-3)
    # the grid covers the top face (a 5 mm margin around 4.5 cm reaches its edge): 1/6 of the box's area
    assert r["coverage"] == pytest.approx(1 / 6, abs=0.02)


def test_view_stats_known_answer(tmp_path):
    """One video: two frames at 0.5 m and 0.7 m from the orbit centre; masks with a 10×20 and a 7×3 box."""
    K = np.array([[100.0, 0, 39.5], [0, 100.0, 29.5], [0, 0, 1]])
    centre = np.array([0.0, 0.0, 0.05])
    w = VideoWriter(tmp_path / "videos" / "000000")
    for fid, dist in ((0, 0.5), (1, 0.7)):
        inst = np.zeros((60, 80), np.uint16)
        inst[10:20, 5:25] = 1
        if fid == 0:
            inst[40:47, 50:53] = 2
        T = look_at(centre + [dist, 0, 0], centre)
        w.write_frame(fid, np.zeros((60, 80, 3), np.uint8), np.full((60, 80), 0.5, np.float32), inst, K, T, [])
    w.finish({"instances": {"1": 1, "2": 2}, "orbit": {"center": centre.tolist()}})
    write_dataset_info(tmp_path, {"name": "views", "resolution": [80, 60], "seed": 0, "config": {}, "objects": []})
    v = view_stats(Dataset(tmp_path), "000000", frame_stride=1)
    assert v["camera_distance_m"]["n"] == 2 and v["camera_distance_m"]["max"] == pytest.approx(0.7)
    assert v["camera_distance_m"]["median"] == pytest.approx(0.6)
    assert v["object_px"]["n"] == 3 and v["object_px"]["max"] == 20 and v["object_px"]["median"] == 20
    assert view_stats(Dataset(tmp_path), "000000", frame_stride=2)["object_px"]["n"] == 2  # frame 0 only


@pytest.mark.slow
def test_stats_on_analytic_scenes_match_table2(tmp_path, capsys):
    """The statistics' rows are Table II's per-video scores; contact as placed: the third scene's boxes touch."""
    scenes = two_box_scenes()
    scenes[2][0] = (box((0.06, 0.1, 0.05), (-0.05, 0.06, 0.025)), 2)  # instance 1 against instance 3's face x = −0.08
    ds = Dataset(make_dataset(tmp_path / "analytic", scenes, n_frames=20, width=160, height=120, arc_deg=30))
    models = {vid: {oid: mesh for mesh, oid in objs} for vid, objs in zip(ds.video_ids, scenes)}
    # truncation 3 voxels: the default 8 leaves 10–15 % of these boxes' points > 1 cm off (TSDF artifacts)
    cfg = load_config(OursConfig, overrides=FAST + ["recon.trunc_voxel_multiplier=3"])
    out = tmp_path / "results"
    stats = run_stats(ds, cfg, out, models=models)
    saved = read_json(out / STATS_JSON.format(dataset=ds.name, config_hash=stats["config_hash"]))
    assert saved["overall"] == stats["overall"] and sorted(saved["scenes"]) == ds.video_ids
    assert [stats["scenes"][v]["touching_pairs"] for v in ds.video_ids] == [[], [], [[1, 3]]]
    assert stats["overall"]["touching_pairs"] == 1 and stats["overall"]["objects"] == 7
    records = run_table2(ds, cfg, out, ("lccp", "lccp+symseg", "gt-merging"), models=models, progress=False)
    for rec in records:
        for v in ds.video_ids:
            for k in ("P", "R", "IoU"):
                assert stats["scenes"][v]["rows"][rec["name"]][k] == pytest.approx(rec["per_video"][v][k])
    for v in ds.video_ids:
        s = stats["scenes"][v]
        assert s["reconstruction"]["artifact_share"] < 0.05 and s["reconstruction"]["coverage"] > 0.3
        for o in s["per_object"]["lccp"].values():
            assert o["recall"] + o["pruned"] + o["other"] + o["own_parts"] == pytest.approx(1.0)
    table = format_stats({"dataset": ds.name, **stats}).splitlines()
    assert len(table) == 2 + len(ds.video_ids) + 1 and table[-1].split()[0] == "all"


@pytest.mark.slow
def test_stats_cli(tmp_path, capsys):
    """``evaluate3d --stats`` on a one-scene dataset whose models are on disk (world-placed meshes, mm)."""
    scene = two_box_scenes()[0]
    ds = Dataset(make_dataset(tmp_path / "one", [scene], n_frames=20, arc_deg=30))
    for mesh, oid in scene:
        ds.model_path(oid).parent.mkdir(parents=True, exist_ok=True)
        mesh.copy().apply_scale(1000.0).export(ds.model_path(oid))
    args = ["--data", str(ds.root), "--out", str(tmp_path / "out"), "--stats"]
    assert main(args + [a for x in FAST for a in ("--set", x)]) == 0
    printed = capsys.readouterr().out
    assert "Data statistics of" in printed and "statistics: " in printed
    path = printed.strip().splitlines()[-1].split("statistics: ")[1]
    assert read_json(path)["overall"]["objects"] == 2 and read_json(path)["task"] == "stats"
