"""Results never mix: two datasets of one name stay apart, partial re-runs with other settings get their
own leaderboard row, stale predictions are cleared, finished folds are reused, and Ctrl-C (a real
SIGINT) exits 130 with one line and resumes to the same result."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest

from selfseg.dataset import Dataset
from selfseg.eval.cli import main
from selfseg.eval.folds import EvalOptions, fold_split
from selfseg.eval.leaderboard import load_results
from selfseg.eval.protocol import run_fold
from selfseg.eval.scoring import MethodOutputError
from selfseg.fileio import read_json, write_json
from selfseg.method_api import Method
from selfseg.writers import write_inst

QUICK = ["--frame-stride", "3", "--quiet"]


def evaluate(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def twin(analytic_dataset, tmp_path):
    """A second dataset with the same name and different content (another seed, so other folds too)."""
    root = tmp_path / "twin" / "analytic"
    shutil.copytree(analytic_dataset, root)
    info = read_json(root / "dataset_info.json")
    write_json(root / "dataset_info.json", {**info, "seed": info.get("seed", 0) + 1})
    return root


def test_same_name_datasets_and_partial_reruns_stay_apart(analytic_dataset, twin, tmp_path, capsys):
    out = tmp_path / "res"
    assert evaluate(capsys, "--method", "fg-components", "--data", analytic_dataset, "--out", out, *QUICK)[0] == 0
    first = {p.name: p.read_bytes() for p in (out / "scores/analytic/fg-components").iterdir()}
    code, stdout, err = evaluate(capsys, "--method", "fg-components", "--data", twin, "--out", out, *QUICK)
    assert code == 0, err
    twin_key = next(p.name for p in (out / "scores").iterdir() if p.name != "analytic")
    assert twin_key.startswith("analytic-") and f"scores/{twin_key}/" in stdout.replace(os.sep, "/")
    assert {p.name: p.read_bytes() for p in (out / "scores/analytic/fg-components").iterdir()} == first  # untouched
    # a partial re-run with another setting under the same run name is refused (evaluate --replace replaces)
    code, _, err = evaluate(capsys, "--method", "depth-clustering", "--data", analytic_dataset, "--out", out, *QUICK)
    assert code == 0, err
    run = out / "scores/analytic/depth-clustering"
    kept = {p.name: p.read_bytes() for p in run.iterdir()}
    code, _, err = evaluate(capsys, "--method", "depth-clustering", "--data", analytic_dataset, "--out", out,
                            "--folds", "1", "--set", "distance_m=0.05", *QUICK)
    assert code == 2 and "distance_m 0.01 → 0.05" in err
    assert {p.name: p.read_bytes() for p in run.iterdir()} == kept
    # results folders written before that refusal existed can hold such a mix: the leaderboard still never
    # averages it, each run gets its own row
    rec = json.loads((run / "fold1.json").read_text())
    rec["config"]["distance_m"], rec["config_hash"] = 0.05, "another-config"
    (run / "fold1.json").write_text(json.dumps(rec))
    groups = load_results(out)
    assert set(groups) == {"analytic", twin_key}
    names = sorted(name for _, name in groups["analytic"])
    rows = [n for n in names if n.startswith("depth-clustering")]
    assert len(rows) == 2 and all(" [" in n for n in rows)  # two runs, each with its key
    folds = sorted(len(groups["analytic"]["2d", n]) for n in rows)
    assert folds == [1, 2]
    for n in rows:
        assert len({r["config_hash"] for r in groups["analytic"]["2d", n]}) == 1


def test_stale_predictions_are_cleared_and_finished_folds_reused(analytic_dataset, tmp_path, capsys):
    out = tmp_path / "res"
    ds = Dataset(analytic_dataset)
    vid = fold_split(ds, 0)[1][0]
    stale = out / f"predictions/fg-components/analytic/{vid}/000999.png"
    write_inst(stale, np.ones((ds.height, ds.width), np.uint16))
    assert evaluate(capsys, "--method", "fg-components", "--data", analytic_dataset, "--out", out, "--folds", "0",
                    *QUICK)[0] == 0
    assert not stale.exists() and sorted(p.name for p in stale.parent.iterdir()) == ["000000.png", "000003.png"]
    before = (out / "scores/analytic/fg-components/fold0.json").read_bytes()
    code, _, err = evaluate(capsys, "--method", "fg-components", "--data", analytic_dataset, "--out", out,
                                "--folds", "0", "--frame-stride", "3")
    assert code == 0 and "reusing" in err
    assert (out / "scores/analytic/fg-components/fold0.json").read_bytes() == before


class HugeIds(Method):
    name = "huge-ids"

    def segment(self, video, frame_id, fg_mask):
        return fg_mask.astype(np.int64) * 70000


def test_ids_out_of_range_are_one_line_errors(analytic_dataset, tmp_path):
    with pytest.raises(MethodOutputError, match=r"\[0, 65535\].*70000"):
        run_fold(HugeIds, None, Dataset(analytic_dataset), 0, tmp_path, EvalOptions(frame_stride=3, n_boot=10),
                 progress=False)


# depth-clustering made slow (0.3 s a frame), so the run cannot finish its last folds before the signal
# lands, however loaded the machine (plain depth-clustering scored folds 1–2 within the 50 ms poll in CI)
SLOW_METHOD = """
import time
from selfseg.baselines.simple import DepthClustering

class SlowDepthClustering(DepthClustering):
    name = "slow-depth-clustering"

    def segment(self, video, frame_id, fg_mask):
        time.sleep(0.3)
        return super().segment(video, frame_id, fg_mask)
"""


@pytest.mark.slow
def test_ctrl_c_exits_130_with_one_line_and_resumes_identically(analytic_dataset, tmp_path, ctrl_c_child):
    (tmp_path / "userpath").mkdir()
    (tmp_path / "userpath" / "slowmethod.py").write_text(SLOW_METHOD)
    env = {**os.environ, "PYTHONPATH": str(tmp_path / "userpath")}
    evaluate_bin = [sys.executable, "-m", "selfseg.eval.cli", "--method", "slowmethod:SlowDepthClustering",
                    "--name", "slow-depth-clustering", "--data", str(analytic_dataset), "--frame-stride", "1", "--quiet"]
    out = tmp_path / "interrupted"
    proc = subprocess.Popen(evaluate_bin + ["--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, **ctrl_c_child)
    fold0 = out / "scores/analytic/slow-depth-clustering/fold0.json"
    deadline = time.monotonic() + 120
    while not fold0.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does: the whole process group
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert len(err.strip().splitlines()) == 1 and "interrupted" in err, err
    assert fold0.exists() and not (out / "scores/analytic/slow-depth-clustering/fold2.json").exists()
    resumed = subprocess.run(evaluate_bin + ["--out", str(out)], capture_output=True, text=True, timeout=300, env=env)
    fresh = subprocess.run(evaluate_bin + ["--out", str(tmp_path / "fresh")], capture_output=True, text=True,
                           timeout=300, env=env)
    assert resumed.returncode == 0 and fresh.returncode == 0, resumed.stderr + fresh.stderr
    for k in range(3):
        a, b = (json.loads((root / f"scores/analytic/slow-depth-clustering/fold{k}.json").read_text())
                for root in (out, tmp_path / "fresh"))
        assert a["metrics"] == b["metrics"] and a["per_video"] == b["per_video"]


def test_a_changed_depth_frame_invalidates_reuse_and_the_view(analytic_dataset, tmp_path, capsys):
    """Identity covers every frame: a copy whose test depth frame was replaced (JSON unchanged) is not
    reused, under the same run name or a new one, and its unlabeled view links the new frame."""
    root = tmp_path / "copy" / "analytic"
    shutil.copytree(analytic_dataset, root)
    out = tmp_path / "res"
    args = ["--method", "fg-components", "--data", root, "--out", out, "--folds", "0", "--frame-stride", "3"]
    assert evaluate(capsys, *args, "--quiet")[0] == 0
    code, _, err = evaluate(capsys, *args)
    assert code == 0 and "reusing" in err
    vid = fold_split(Dataset(root), 0)[1][0]
    frame = root / "videos" / vid / "depth" / "000000.png"
    depth = cv2.imread(str(frame), cv2.IMREAD_UNCHANGED)
    depth[depth > 0] -= 100  # everything 1 cm nearer
    frame.unlink()
    assert cv2.imwrite(str(frame), depth)
    for name in ("fg-components", "renamed"):
        code, _, err = evaluate(capsys, *args, "--name", name)
        assert code == 0 and "reusing" not in err, err
    views = sorted((out / "work/_views").iterdir())
    assert len(views) == 2
    new_view = next(v for v in views if Dataset(root).content_hash() in v.name)
    assert (new_view / "analytic/videos" / vid / "depth/000000.png").read_bytes() == frame.read_bytes()
    hashes = {read_json(p)["dataset"]["content_hash"] for p in (out / "scores").rglob("fold0.json")}
    assert Dataset(root).content_hash() in hashes


def test_a_method_given_labels_gets_its_folds_own_stage_root(analytic_dataset, tmp_path):
    """Label-free registered methods share one stage root per dataset; one given labels (ours-gt-merging) writes
    its stages in its fold's own folder, never where a label-free method or another fold reads (measured: sharing
    one root, its camera files with the dataset's poses gave other stage keys, and the two sides rebuilt each
    other's stages while the other read them: 'segmaps/000055.png: missing file')."""
    from selfseg.eval.mounts import method_stage_root

    ds = Dataset(analytic_dataset)
    fmt = lambda name, k: {"name": name, "dataset": ds.name, "fold": k}  # noqa: E731
    shared = {method_stage_root(tmp_path, ds, False, "none", fmt(n, k)) for n in ("ours", "ours-v3") for k in (0, 1)}
    assert len(shared) == 1
    (shared,) = shared
    assert shared.is_relative_to(tmp_path.resolve()) and shared.name.endswith("-noposes")
    assert method_stage_root(tmp_path, ds, True, "none", fmt("ours", 0)) != shared
    labeled = [method_stage_root(tmp_path, ds, False, "train", fmt("ours-gt-merging", k)) for k in (0, 1)]
    assert labeled[0] != labeled[1]
    for k, root in enumerate(labeled):
        assert root == (tmp_path / "work" / "ours-gt-merging" / ds.name / f"fold{k}" / "_stages").resolve()
        assert not root.is_relative_to(shared) and not shared.is_relative_to(root)
