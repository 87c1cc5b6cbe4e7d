"""generate_scenes safety: --overwrite deletes only what the dataset format owns; bad seeds are one line."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
import trimesh

from selfseg.generate.cli import PROGRESS_FILE, GenerateError, main, prepare_output
from selfseg.generate.presets import preset_config


def test_overwrite_keeps_user_files(tmp_path, capsys):
    out = tmp_path / "data"
    owned = ["dataset_info.json", PROGRESS_FILE, "manifest.json", "models/models_info.json", "models/obj_000001.ply",
             "videos/000000/rgb/000000.png", "videos/000000/depth/000000.png", "videos/000000/mask_inst/000000.png",
             "videos/000000/scene_camera.json", "videos/000000/scene_gt.json", "videos/000000/scene_info.json",
             "videos/.000001.x.partial/rgb/000000.png"]
    mine = ["notes.txt", "models/my_mesh.obj", "videos/extra/keep.png"]
    for rel in owned + mine:
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_text("x")
    (out / "dataset_info.json").write_text(json.dumps({"config": {}, "generator_version": "0"}))
    prepare_output(out, preset_config("tiny"), overwrite=True)
    err = capsys.readouterr().err
    assert all((out / rel).read_text() == "x" for rel in mine)
    assert not any((out / rel).exists() for rel in owned)
    assert not (out / "videos/.000001.x.partial").exists()
    assert "removed 12 dataset entries" in err and "notes.txt" in err and len(err.strip().splitlines()) == 1


def _fake_dataset(out, cfg, files) -> None:
    """A dataset record of ``cfg`` (as generate_scenes writes it) and placeholder ``files``."""
    from selfseg.config import to_dict
    from selfseg.generate.presets import GENERATOR_VERSION

    for rel in files:
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_text("x")
    (out / "dataset_info.json").write_text(json.dumps({"config": to_dict(cfg), "generator_version": GENERATOR_VERSION}))


@pytest.mark.parametrize("user_file", ["videos/000000/my_labels.csv", "videos/000001/depth/notes.txt"])
def test_overwrite_refuses_to_empty_a_video_holding_a_user_file(tmp_path, capsys, user_file):
    """Emptying such a video left a folder that counted as a finished scene: 2 of 3 videos, exit 0."""
    out = tmp_path / "data"
    frames = [f"videos/{v:06d}/{sub}/000000.png" for v in range(2) for sub in ("rgb", "depth", "mask_inst")]
    _fake_dataset(out, preset_config("tiny", scenes=3), frames + [user_file])
    before = sorted(p for p in out.rglob("*") if p.is_file())
    assert main(["--preset", "tiny", "--scenes", "3", "--out", str(out), "--overwrite", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(out / user_file) in err and "--overwrite" in err
    assert sorted(p for p in out.rglob("*") if p.is_file()) == before  # nothing deleted


def test_an_incomplete_video_is_not_counted_as_done(tmp_path, capsys):
    out = tmp_path / "data"
    cfg = preset_config("tiny", scenes=2, frames=4)
    complete = [t.format(frame_id=f) for t in ("videos/000000/rgb/{frame_id:06d}.png",
                                               "videos/000000/depth/{frame_id:06d}.png",
                                               "videos/000000/mask_inst/{frame_id:06d}.png") for f in cfg.frame_ids]
    complete += [f"videos/000000/{n}.json" for n in ("scene_camera", "scene_gt", "scene_info")]
    _fake_dataset(out, cfg, complete)
    prepare_output(out, cfg, overwrite=False)  # scene 0 is complete: resumable
    (out / "videos/000000/depth/000002.png").unlink()
    (out / "videos/000001/rgb").mkdir(parents=True)
    (out / "videos/000001/rgb/000000.png").write_text("x")
    for scene in ("000000", "000001"):
        with pytest.raises(GenerateError, match="not a complete scene") as e:
            prepare_output(out, cfg, overwrite=False)
        assert f"{out}/videos/{scene}/" in str(e.value)
        shutil.rmtree(out / "videos" / scene)


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
    """One 40-frame Cycles scene: Ctrl-C after its first frames are on disk ends the run within a few frames'
    time (not after the scene's 40), rc 130; the resumed dataset is byte-identical to an uninterrupted one.
    40 frames, so that the rest of the scene outlasts the 2 s allowed for shutdown even when a frame takes
    only 0.12 s (an unloaded CI machine; with 20 frames the test could not tell the two apart there)."""
    cmd = [sys.executable, "-m", "selfseg.generate.cli", "--preset", "tiny", "--renderer", "cycles", "--scenes", "1",
           "--frames", "40", "--quiet"]
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
    assert took < 3 * frame_s + 2.0 < 37 * frame_s, (took, frame_s)  # the rest of the scene: about 37 frames
    assert not out.joinpath("videos").exists() or not any(out.joinpath("videos").iterdir())
    resumed = subprocess.run(cmd + ["--out", str(out)], capture_output=True, text=True, timeout=900)
    fresh = subprocess.run(cmd + ["--out", str(tmp_path / "fresh")], capture_output=True, text=True, timeout=900)
    assert resumed.returncode == 0 and fresh.returncode == 0, resumed.stderr + fresh.stderr
    files = sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file())
    assert len(files) > 60 and files == sorted(p.relative_to(tmp_path / "fresh")
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
