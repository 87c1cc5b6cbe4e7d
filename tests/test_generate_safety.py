"""generate_scenes safety: --overwrite deletes only what the dataset format owns; bad seeds are one line."""
from __future__ import annotations

import json

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
