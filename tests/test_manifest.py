"""The content manifest: every file's size and sha256; the dataset identity follows any changed frame."""
from __future__ import annotations

import os
import shutil

import pytest

from selfseg.dataset import Dataset, geometry_hash
from selfseg.generate.cli import main as generate_scenes
from selfseg.fileio import hash_json
from selfseg.manifest import MANIFEST, content_hash, read_manifest, verify, write_manifest


@pytest.fixture
def data(analytic_dataset, tmp_path, monkeypatch):
    monkeypatch.setenv("SELFSEG_CACHE", str(tmp_path / "cache"))
    root = tmp_path / "analytic"
    shutil.copytree(analytic_dataset, root)
    return root


def _flip_byte(path, keep_stat: bool = False) -> None:
    """Change the last byte of ``path`` in place (same size); optionally restore its mtime."""
    st = path.stat()
    data = bytearray(path.read_bytes())
    data[-1] ^= 1
    with open(path, "r+b") as f:
        f.write(bytes(data))
    if keep_stat:
        os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))


def test_manifest_lists_every_file_and_its_hash_is_the_identity(data):
    digest = write_manifest(data)
    files = read_manifest(data)["files"]
    assert set(files) == {p.relative_to(data).as_posix() for p in data.rglob("*") if p.is_file()} - {MANIFEST}
    assert any(p.startswith("videos/000000/depth/") for p in files)
    assert content_hash(data) == digest == Dataset(data).content_hash()
    assert verify(data) == (digest, [])


def test_a_changed_depth_frame_changes_the_identity_and_fails_verify(data):
    digest = write_manifest(data)
    frame = data / "videos/000001/depth/000003.png"
    _flip_byte(frame)
    assert content_hash(data) != digest  # the cheap scan sees the new mtime
    assert verify(data, full=False)[1] == ["videos/000001/depth/000003.png: content differs from the manifest"]
    _flip_byte(frame)  # back: the same identity again
    assert content_hash(data) == digest


def test_only_the_full_verify_sees_a_change_that_keeps_size_and_mtime(data):
    digest = write_manifest(data)
    _flip_byte(data / "videos/000002/rgb/000000.png", keep_stat=True)
    assert content_hash(data) == digest  # the cheap check trusts size, mtime and inode
    assert verify(data, full=True)[1] == ["videos/000002/rgb/000000.png: content differs from the manifest"]


def test_generate_scenes_verify_command(data, capsys):
    assert generate_scenes(["--verify", str(data)]) == 2  # no manifest yet
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"{data / MANIFEST}: file not found" in err
    digest = write_manifest(data)
    assert generate_scenes(["--verify", str(data)]) == 0
    assert capsys.readouterr().out.strip().startswith(f"{data}: every file matches manifest {digest} (geometry hash ")
    (data / "videos/000000/mask_inst/000001.png").unlink()
    (data / "notes.txt").write_text("mine")
    assert generate_scenes(["--verify", str(data)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(data / "notes.txt") in err and "1 more" in err and digest in err


def test_verify_names_rgb_only_differences_and_the_geometry_hash_ignores_them(data, capsys):
    """Another CPU type renders RGB a few 8-bit values apart: --verify names that class (exit 3) and the geometry
    hash (every file but the RGB frames) stays; any other difference is a plain mismatch (exit 1)."""
    digest = write_manifest(data)
    geometry = geometry_hash(read_manifest(data)["files"])
    assert generate_scenes(["--verify", str(data)]) == 0
    assert capsys.readouterr().out.strip() == f"{data}: every file matches manifest {digest} (geometry hash {geometry})"
    _flip_byte(data / "videos/000000/rgb/000001.png")
    _flip_byte(data / "videos/000002/rgb/000000.png")
    assert geometry_hash(read_manifest(data)["files"]) == geometry
    assert generate_scenes(["--verify", str(data)]) == 3
    out = capsys.readouterr().out.strip()
    n_rgb = len(list(data.glob("videos/*/rgb/*.png")))
    assert len(out.splitlines()) == 1 and f"matches manifest {digest} (geometry hash {geometry})" in out
    assert f"2 of {n_rgb} RGB frames differ" in out
    _flip_byte(data / "videos/000001/depth/000003.png")  # a depth frame too: no longer the RGB-only class
    assert generate_scenes(["--verify", str(data)]) == 1
    assert "depth/000003.png: content differs" in capsys.readouterr().err
    _flip_byte(data / "videos/000001/depth/000003.png")
    (data / "videos/000000/rgb/000001.png").unlink()  # a missing RGB frame is not a rendering difference either
    assert generate_scenes(["--verify", str(data)]) == 1


def test_stage_keys_follow_the_frames_without_reading_ground_truth(data):
    from selfseg.guard import ground_truth_forbidden
    from selfseg.method.background import BackgroundConfig
    from selfseg.method.embed_method import video_key
    from selfseg.method.recon_stage import recon_key
    from selfseg.method.reconstruct import ReconConfig

    def keys(vid):
        v = Dataset(data).video(vid)
        with ground_truth_forbidden(data):  # raises if the keys touched mask_inst/ or scene_gt.json
            return hash_json(recon_key(v, ReconConfig(), BackgroundConfig())), hash_json(video_key(v))

    before = {vid: keys(vid) for vid in ("000000", "000001")}
    _flip_byte(data / "videos/000001/depth/000002.png")
    assert keys("000000") == before["000000"]
    assert keys("000001")[0] != before["000001"][0] and keys("000001")[1] != before["000001"][1]
