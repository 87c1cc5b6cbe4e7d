"""generate_scenes: presets, format round trip, determinism, resume and bad-input handling."""
import json
import math
import shutil
import subprocess
import sys
from collections import Counter

import numpy as np
import pytest

from selfseg.dataset import DEPTH_SCALE_MM, Dataset
from selfseg.generate.cli import main
from selfseg.generate.objects import PAPER_SUBSET
from selfseg.generate.presets import preset_config
from selfseg.generate.scene import camera_orbit, choose_objects, scene_seed
from selfseg.manifest import read_manifest, verify

ARGS = ["--preset", "tiny", "--scenes", "2", "--frames", "2", "--resolution", "64x48", "--objects-per-scene", "3",
        "--renderer", "workbench", "--seed", "5", "--quiet"]


def _run(out, *extra) -> int:
    return main([*ARGS, "--out", str(out), *extra])


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    out = tmp_path_factory.mktemp("gen") / "ds"
    assert _run(out) == 0
    return out


def test_generated_dataset_has_a_manifest_of_every_file(generated):
    digest, problems = verify(generated)
    files = read_manifest(generated)["files"]
    assert problems == [] and digest == Dataset(generated).content_hash()
    assert len(files) == 2 * 2 * 3 + 2 * 3 + 1 + 1 + len(preset_config("tiny").object_pool)  # frames, JSON, info, models


def _rotation_deg(Ta: np.ndarray, Tb: np.ndarray) -> float:
    R = Ta[:3, :3].T @ Tb[:3, :3]
    return math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


def test_presets():
    tiny = preset_config("tiny")
    assert tiny.scenes * len(tiny.frame_ids) <= 200 and tiny.width * tiny.height <= 160 * 120
    # objects reappear across scenes
    counts = Counter(i for s in range(tiny.scenes)
                     for i in choose_objects(np.random.default_rng(scene_seed(tiny.seed, s)), len(tiny.object_pool),
                                             tiny.objects_per_scene))
    assert sum(c >= 2 for c in counts.values()) >= len(tiny.object_pool) // 2
    # the view changes by at most 2° between frames, so frame-to-model tracking works
    cams, orbit = camera_orbit(tiny.orbit, tiny.frames, np.array([0.0, 0.0, 0.03]), np.random.default_rng(0))
    assert max(_rotation_deg(a, b) for a, b in zip(cams, cams[1:])) <= 2.0
    assert all(np.linalg.norm(T[:3, 3] - [0, 0, 0.03]) > 0.4 for T in cams)
    paper = preset_config("paper-synthetic", frame_step=4)
    assert (paper.scenes, paper.frames, paper.objects_per_scene, paper.width, paper.height) == (36, 800, 12, 640, 480)
    assert paper.object_pool == list(PAPER_SUBSET) and len(PAPER_SUBSET) == 17
    assert paper.frame_ids[:3] == [0, 4, 8] and len(paper.frame_ids) == 200
    assert paper.render.renderer == "cycles"


@pytest.mark.slow
def test_format_round_trip(generated):
    ds = Dataset(generated)
    assert ds.video_ids == ["000000", "000001"] and (ds.width, ds.height) == (64, 48)
    assert ds.info["config"]["seed"] == 5 and ds.info["generator_version"]
    names = [o["name"] for o in ds.info["objects"]]
    assert names == preset_config("tiny").object_pool
    assert set(ds.models_info()) == {o["obj_id"] for o in ds.info["objects"]}
    assert all(ds.model_path(o["obj_id"]).is_file() for o in ds.info["objects"])
    for vid in ds.video_ids:
        video = ds.labeled(vid)
        inst_to_obj = video.instance_to_object()
        assert 1 <= len(inst_to_obj) <= 3 and sorted(inst_to_obj) == list(range(1, len(inst_to_obj) + 1))
        for fid in video.frame_ids:
            assert {(g["inst_id"], g["obj_id"]) for g in video.gt(fid)} == set(inst_to_obj.items())
            depth, inst = video.depth_m(fid), video.inst(fid)
            units = depth * 1000.0 / DEPTH_SCALE_MM
            assert np.allclose(units, np.rint(units), atol=1e-2)  # quantised to depth_scale steps
            assert set(np.unique(inst)) <= {0, *inst_to_obj} and (depth[inst > 0] > 0).all()
            assert video.rgb(fid).shape == (48, 64, 3)
        assert video.scene_info["table_plane"] == [0.0, 0.0, 1.0, 0.0]
    assert not (generated / ".generate.json").exists()


@pytest.mark.slow
def test_same_seed_same_scenes(generated, tmp_path):
    again = tmp_path / "again"
    assert _run(again) == 0
    a, b = Dataset(generated), Dataset(again)
    assert a.content_hash() == b.content_hash()
    for vid in a.video_ids:
        va, vb = a.labeled(vid), b.labeled(vid)
        for fid in va.frame_ids:
            assert np.array_equal(va.depth_m(fid), vb.depth_m(fid))
            assert np.array_equal(va.inst(fid), vb.inst(fid))
            assert np.array_equal(va.rgb(fid), vb.rgb(fid))


@pytest.mark.slow
def test_resume_skips_completed_scenes(generated, tmp_path, capsys):
    out = tmp_path / "ds"
    shutil.copytree(generated, out)
    kept = out / "videos/000000/scene_camera.json"
    stamp = kept.stat().st_mtime_ns
    shutil.rmtree(out / "videos/000001")
    (out / "videos/.000001.abc.partial").mkdir()  # left by an interrupted run
    (out / "dataset_info.json").unlink()  # an unfinished dataset records its config here instead
    info = Dataset(generated).info
    (out / ".generate.json").write_text(json.dumps({k: info[k] for k in ("config", "generator_version")}))
    capsys.readouterr()
    assert _run(out) == 0
    assert "1 scenes generated, 1 already complete" in capsys.readouterr().out
    assert kept.stat().st_mtime_ns == stamp
    assert not (out / "videos/.000001.abc.partial").exists() and not (out / ".generate.json").exists()
    assert Dataset(out).content_hash() == Dataset(generated).content_hash()
    assert _run(out) == 0
    assert "0 scenes generated, 2 already complete" in capsys.readouterr().out


@pytest.mark.slow
def test_overwrite_replaces_a_dataset(generated, tmp_path):
    out = tmp_path / "ds"
    shutil.copytree(generated, out)
    assert main([*ARGS, "--out", str(out), "--scenes", "1", "--frames", "1", "--overwrite"]) == 0
    ds = Dataset(out)
    assert ds.video_ids == ["000000"] and ds.info["config"]["frames"] == 1


def _fails(capsys, argv, match: str) -> None:
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "error" in err and match in err, err


@pytest.mark.slow
def test_bad_input_exits_2_and_writes_nothing(generated, tmp_path, capsys):
    new = tmp_path / "new"
    _fails(capsys, [*ARGS, "--out", str(new), "--resolution", "0x48"], "width")
    _fails(capsys, [*ARGS, "--out", str(new), "--objects-per-scene", "7"], "only 6 objects")
    empty = tmp_path / "empty_objects"
    empty.mkdir()
    _fails(capsys, [*ARGS, "--out", str(new), "--objects", str(empty)], "no meshes")
    bad = tmp_path / "bad_objects"
    bad.mkdir()
    (bad / "broken.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    _fails(capsys, [*ARGS, "--out", str(new), "--objects", str(bad)], "broken.ply")
    assert not new.exists()
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    _fails(capsys, [*ARGS, "--out", str(foreign)], "not a selfseg dataset")
    _fails(capsys, [*ARGS, "--out", str(foreign), "--overwrite"], "refusing")
    assert (foreign / "notes.txt").read_text() == "mine"
    before = Dataset(generated).content_hash()
    _fails(capsys, [*ARGS, "--out", str(generated), "--seed", "6"], "different config (differs in: seed)")
    assert Dataset(generated).content_hash() == before
    (generated / "videos" / "stray").mkdir()
    try:
        _fails(capsys, [*ARGS, "--out", str(generated)], "videos/stray")
    finally:
        (generated / "videos" / "stray").rmdir()


def test_console_exit_code(tmp_path):
    r = subprocess.run([sys.executable, "-m", "selfseg.generate.cli", "--out", str(tmp_path / "x"),
                        "--resolution", "64x0"], capture_output=True, text=True)
    assert r.returncode == 2 and "height must be at least 1" in r.stderr
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_user_objects_folder(tmp_path):
    """--objects: one object per mesh file (OBJ, PLY, GLB in metres), listed by name in dataset_info."""
    import trimesh

    objs = tmp_path / "objs"
    objs.mkdir()
    trimesh.creation.box(extents=(0.08, 0.06, 0.05)).export(objs / "block.obj")
    trimesh.creation.cylinder(radius=0.03, height=0.1, sections=24).export(objs / "tube.ply")
    trimesh.creation.icosphere(2, radius=0.04).export(objs / "orb.glb")
    out = tmp_path / "ds"
    assert main([*ARGS, "--out", str(out), "--objects", str(objs), "--objects-per-scene", "2", "--scenes", "1",
                 "--frames", "1"]) == 0
    ds = Dataset(out)
    assert [o["name"] for o in ds.info["objects"]] == ["block", "orb", "tube"]
    assert all(o["source"].startswith("user:") for o in ds.info["objects"])
    video = ds.labeled("000000")
    assert set(np.unique(video.inst(0))) - {0} <= set(video.instance_to_object())
    assert (video.inst(0) > 0).any()


def test_object_pool_option(tmp_path, capsys):
    from selfseg.generate.cli import build_parser, config_from_args, main
    args = build_parser().parse_args(["--preset", "tiny", "--out", str(tmp_path / "a"), "--object-pool", "cube, book,jar,egg"])
    assert config_from_args(args).object_pool == ["cube", "book", "jar", "egg"]
    assert main(["--preset", "tiny", "--out", str(tmp_path / "b"), "--object-pool", "cube,nonsense"]) == 2
    assert "nonsense" in capsys.readouterr().err and not (tmp_path / "b" / "dataset_info.json").exists()
