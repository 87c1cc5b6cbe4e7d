"""generate_scenes safety: --overwrite deletes only what the dataset format owns; bad seeds are one line."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest
import trimesh

from selfseg.generate.cli import PROGRESS_FILE, main, prepare_output
from selfseg.generate.presets import preset_config


def test_overwrite_keeps_user_files(tmp_path, capsys):
    out = tmp_path / "data"
    owned = ["dataset_info.json", PROGRESS_FILE, "models/models_info.json", "models/obj_000001.ply",
             "videos/000000/rgb/000000.png", "videos/000000/depth/000000.png", "videos/000000/mask_inst/000000.png",
             "videos/000000/scene_camera.json", "videos/000000/scene_gt.json", "videos/000000/scene_info.json",
             "videos/.000001.x.partial/rgb/000000.png"]
    mine = ["notes.txt", "models/my_mesh.obj", "videos/000000/my_labels.csv", "videos/extra/keep.png"]
    for rel in owned + mine:
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_text("x")
    (out / "dataset_info.json").write_text(json.dumps({"config": {}, "generator_version": "0"}))
    prepare_output(out, preset_config("tiny"), overwrite=True)
    err = capsys.readouterr().err
    assert all((out / rel).read_text() == "x" for rel in mine)
    assert not any((out / rel).exists() for rel in owned)
    assert not (out / "videos/.000001.x.partial").exists()
    assert "removed 11 dataset entries" in err and "notes.txt" in err and len(err.strip().splitlines()) == 1


def test_negative_seed_is_one_line(tmp_path, capsys):
    code = main(["--preset", "tiny", "--seed", "-1", "--out", str(tmp_path / "d"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "seed" in err and "-1" in err
    assert not (tmp_path / "d").exists()


@pytest.mark.slow
def test_ctrl_c_during_cycles_exits_130_and_resumes_identically(tmp_path, ctrl_c_child):
    cmd = [sys.executable, "-m", "selfseg.generate.cli", "--preset", "tiny", "--renderer", "cycles", "--scenes", "3",
           "--frames", "6", "--quiet"]
    out = tmp_path / "interrupted"
    proc = subprocess.Popen(cmd + ["--out", str(out)], stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                            **ctrl_c_child)
    deadline = time.monotonic() + 240
    while not list(out.glob("videos/.*.partial/rgb/*.png")) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    t0 = time.monotonic()
    os.killpg(proc.pid, signal.SIGINT)  # a terminal's Ctrl-C, mid-scene, Cycles rendering
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and time.monotonic() - t0 < 10, err
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("pybullet build time")]  # pybullet's banner
    assert len(lines) == 1 and "interrupted" in lines[0]
    resumed = subprocess.run(cmd + ["--out", str(out)], capture_output=True, text=True, timeout=300)
    fresh = subprocess.run(cmd + ["--out", str(tmp_path / "fresh")], capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0 and fresh.returncode == 0, resumed.stderr + fresh.stderr
    files = sorted(p.relative_to(out) for p in out.rglob("videos/*/*/*.png"))
    assert len(files) == 3 * 6 * 3
    assert all((out / f).read_bytes() == (tmp_path / "fresh" / f).read_bytes() for f in files)


@pytest.mark.slow
def test_ctrl_c_mid_scene_returns_within_a_few_frames(tmp_path, ctrl_c_child):
    """One 30-frame Cycles scene: Ctrl-C after its first frames are on disk ends the run within a few frames'
    time (not after the scene's 30), rc 130; the resumed dataset is byte-identical to an uninterrupted one."""
    cmd = [sys.executable, "-m", "selfseg.generate.cli", "--preset", "tiny", "--renderer", "cycles", "--scenes", "1",
           "--frames", "30", "--quiet"]
    out = tmp_path / "interrupted"
    proc = subprocess.Popen(cmd + ["--out", str(out)], stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                            **ctrl_c_child)
    first = None  # (frames on disk, when) once the first frame is there
    deadline = time.monotonic() + 240
    while True:
        assert proc.poll() is None and time.monotonic() < deadline, "the scene finished before it was interrupted"
        n = len(list(out.glob("videos/.*.partial/rgb/*.png")))
        if n and first is None:
            first = (n, time.monotonic())
        if first is not None and n >= first[0] + 2:
            frame_s = (time.monotonic() - first[1]) / (n - first[0])  # seconds per frame, measured
            break
        time.sleep(0.02)
    t0 = time.monotonic()
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    took = time.monotonic() - t0
    assert proc.returncode == 130, err
    assert took < 3 * frame_s + 2.0 < 27 * frame_s, (took, frame_s)  # the rest of the scene: about 27 frames
    assert not out.joinpath("videos").exists() or not any(out.joinpath("videos").iterdir())
    resumed = subprocess.run(cmd + ["--out", str(out)], capture_output=True, text=True, timeout=300)
    fresh = subprocess.run(cmd + ["--out", str(tmp_path / "fresh")], capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0 and fresh.returncode == 0, resumed.stderr + fresh.stderr
    files = sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file())
    assert len(files) > 90 and files == sorted(p.relative_to(tmp_path / "fresh")
                                               for p in (tmp_path / "fresh").rglob("*") if p.is_file())
    assert all((out / f).read_bytes() == (tmp_path / "fresh" / f).read_bytes() for f in files)


def _sheet():
    return trimesh.Trimesh([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0]], [[0, 1, 2], [0, 2, 3]])


BAD_MESHES = {  # name: (mesh, words the one-line error must contain)
    "flat_sheet": (_sheet, "flat"),
    "dense": (lambda: trimesh.creation.icosphere(subdivisions=7, radius=0.05), "faces"),
    "box_1p9m": (lambda: trimesh.creation.box(extents=(1.9, 0.3, 0.3)), "at most 0.5 m"),
    "box_1p5units": (lambda: trimesh.creation.box(extents=(1.5, 1.0, 1.0)), "at most 0.5 m"),
    "box_cm": (lambda: trimesh.creation.box(extents=(10.0, 8.0, 6.0)), "centimetres"),
    "box_mm": (lambda: trimesh.creation.box(extents=(100.0, 80.0, 60.0)), "millimetres"),
    "box_half_mm": (lambda: trimesh.creation.box(extents=(0.0005, 0.0005, 0.0005)), "too small"),
}


@pytest.mark.parametrize("name", list(BAD_MESHES))
def test_bad_mesh_is_one_line_rc2_within_10_s(tmp_path, capsys, name):
    make, words = BAD_MESHES[name]
    objects = tmp_path / "objects"
    objects.mkdir()
    make().export(objects / f"{name}.ply")
    t0 = time.monotonic()
    code = main(["--preset", "tiny", "--objects", str(objects), "--objects-per-scene", "1",
                 "--out", str(tmp_path / "d"), "--quiet"])
    err = capsys.readouterr().err
    assert time.monotonic() - t0 < 10
    assert code == 2 and len(err.strip().splitlines()) == 1 and f"{name}.ply" in err and words in err, err
    assert not (tmp_path / "d").exists()
