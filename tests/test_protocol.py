"""The protocol: folds, what methods may see, oracle end to end, re-scoring from disk."""
import json
import subprocess
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from selfseg.baselines.external import ExternalConfig, ExternalPredictions
from selfseg.dataset import MASK_INST, SCENE_GT, Dataset, DatasetError, LabeledVideo, PosesNotGiven, read_inst
from selfseg.eval.folds import EvalOptions, fold_split, make_folds, select_test_frames
from selfseg.eval.layout import WORK_DIR
from selfseg.eval.metrics import METRIC_KEYS
from selfseg.eval.protocol import run_fold
from selfseg.eval.provenance import cpu_model, git_info
from selfseg.guard import GroundTruthAccessError
from selfseg.method_api import Method
from selfseg.registry import get_method_class
from selfseg.writers import write_inst

FAST = EvalOptions(frame_stride=2, n_boot=100)


def fake_dataset(n: int, seed: int, folds=None):
    info = {"seed": seed} if folds is None else {"seed": seed, "folds": folds}
    return SimpleNamespace(video_ids=[f"{i:06d}" for i in range(n)], seed=seed, info=info, root=Path("/nowhere"))


@pytest.mark.parametrize("n", [3, 7, 36])
def test_folds_partition_videos(n):
    ds = fake_dataset(n, seed=5)
    folds = make_folds(ds)
    assert sorted(v for f in folds for v in f) == ds.video_ids  # every video tested exactly once
    assert max(map(len, folds)) - min(map(len, folds)) <= 1
    assert make_folds(fake_dataset(n, seed=5)) == folds  # deterministic
    for k in range(3):
        train, test = fold_split(ds, k)
        assert not set(train) & set(test) and sorted(train + test) == ds.video_ids


def test_stored_folds_are_used_and_checked():
    ds = fake_dataset(3, 0, folds=[["000002"], ["000000"], ["000001"]])
    assert fold_split(ds, 0) == (["000000", "000001"], ["000002"])
    with pytest.raises(DatasetError, match="folds"):
        make_folds(fake_dataset(3, 0, folds=[["000000"], ["000000"], ["000001"]]))


def test_frame_selection():
    assert select_test_frames(list(range(25)), 10, None) == [0, 10, 20]
    assert select_test_frames(list(range(25)), 10, 2) == [0, 10]


class Recorder(Method):
    """Records what it was given in its workdir (it runs in its own process); segments with one segment."""

    name = "recorder"

    def _note(self, key, values):
        path = self.workdir / "seen.json"
        seen = json.loads(path.read_text()) if path.is_file() else {}
        seen[key] = sorted(set(seen.get(key, [])) | set(values))
        path.write_text(json.dumps(seen))

    def fit(self, train_videos):
        self._note("fit", [v.video_id for v in train_videos])
        self._note("types", [type(v).__name__ for v in train_videos])
        with pytest.raises(PosesNotGiven):
            train_videos[0].T_world_cam(0)

    def segment(self, video, frame_id, fg_mask):
        self._note("test", [video.video_id])
        return fg_mask.astype(np.uint16)


def test_fit_sees_only_training_videos_without_labels(analytic_dataset, tmp_path):
    ds = Dataset(analytic_dataset)
    for k in range(3):
        rec = run_fold(Recorder, None, ds, k, tmp_path, FAST, progress=False)
        seen = json.loads((tmp_path / WORK_DIR.format(name="recorder", dataset=ds.name, fold=k) / "seen.json").read_text())
        assert set(seen["fit"]) == set(rec["train_videos"]) and seen["types"] == ["Video"]
        assert set(seen["test"]) == set(rec["test_videos"])
        assert not set(seen["test"]) & set(seen["fit"])


class CheatOpen(Method):
    """Tries to read the masks of its training videos with plain open()."""

    name = "cheat-open"

    def fit(self, train_videos):
        v = train_videos[0]
        with open(v._root / MASK_INST.format(video_id=v.video_id, frame_id=0), "rb") as f:
            f.read()


class CheatLabeled(Method):
    """Rebuilds a LabeledVideo from the video it is given, at test time."""

    name = "cheat-labeled"

    def segment(self, video, frame_id, fg_mask):
        return LabeledVideo(video._root, video.video_id, video.width, video.height).inst(frame_id)


class CheatJson(Method):
    """Reads scene_gt.json of a training video."""

    name = "cheat-json"

    def fit(self, train_videos):
        v = train_videos[0]
        json.loads(open(v._root / SCENE_GT.format(video_id=v.video_id)).read())


class CheatList(Method):
    """Lists the mask folder."""

    name = "cheat-list"

    def fit(self, train_videos):
        import os
        os.listdir(train_videos[0]._root / "videos" / train_videos[0].video_id / "mask_inst")


@pytest.mark.parametrize("cheat", [CheatOpen, CheatLabeled, CheatJson, CheatList])
def test_no_ground_truth_reaches_the_method(analytic_dataset, tmp_path, cheat):
    with pytest.raises(GroundTruthAccessError):
        run_fold(cheat, None, Dataset(analytic_dataset), 0, tmp_path, FAST, progress=False)
    assert not (tmp_path / "scores").exists()  # nothing is scored for a cheating method


def test_oracle_scores_one_end_to_end_and_rescores_from_disk(analytic_dataset, tmp_path):
    ds = Dataset(analytic_dataset)
    oracle = get_method_class("oracle")
    rec = run_fold(oracle, None, ds, 1, tmp_path, FAST, progress=False)
    assert all(rec["metrics"][k] == 1.0 for k in METRIC_KEYS) and rec["metrics"]["n_frames"] == 3
    saved = json.loads((tmp_path / "scores/analytic/oracle/fold1.json").read_text())
    for key in ("schema_version", "config_hash", "git", "versions", "timings", "per_video", "ci95", "options"):
        assert key in saved
    assert saved["dataset"]["content_hash"] == ds.content_hash() and saved["options"]["frame_stride"] == 2
    lines = (tmp_path / "scores/analytic/oracle/fold1.frames.jsonl").read_text().splitlines()
    assert [json.loads(x)["frame_id"] for x in lines] == [0, 2, 4]
    vid = rec["test_videos"][0]
    pred_dir = tmp_path / "predictions/oracle/analytic"
    assert np.array_equal(read_inst(pred_dir / f"{vid}/000002.png"), ds.labeled(vid).inst(2))

    # scoring from disk: a damaged prediction file lowers the external method's score
    damaged = read_inst(pred_dir / f"{vid}/000002.png")
    damaged[damaged == damaged.max()] = 0
    write_inst(pred_dir / f"{vid}/000002.png", damaged)
    again = run_fold(ExternalPredictions, ExternalConfig(predictions=str(pred_dir)), ds, 1, tmp_path / "re",
                     EvalOptions(frame_stride=2, n_boot=100, name="oracle-rescored"), progress=False)
    assert again["metrics"]["IoU"] < 1.0 and again["per_video"][vid]["n_frames"] == 3


def test_baselines_on_a_hand_made_depth_frame():
    """Two touching boxes 5 cm apart in depth, a third 3 cm to the side; one has a no-depth hole."""
    from selfseg.baselines.simple import DepthClusteringConfig, cluster_depth
    from selfseg.eval.metrics import frame_metrics

    K = np.array([[500.0, 0, 79.5], [0, 500.0, 59.5], [0, 0, 1]])
    gt = np.zeros((120, 160), np.uint16)
    depth = np.zeros((120, 160), np.float32)
    gt[40:80, 20:60], depth[40:80, 20:60] = 1, 0.50
    gt[40:80, 60:90], depth[40:80, 60:90] = 2, 0.55  # touches box 1 in the image, 5 cm behind it
    gt[40:80, 120:150], depth[40:80, 120:150] = 3, 0.50  # 30 px = 3 cm to the side at 0.5 m
    depth[55:60, 30:35] = 0  # no depth: filled from the neighbours
    labels = cluster_depth(depth, K, gt > 0, DepthClusteringConfig(distance_m=0.01))
    assert frame_metrics(labels, gt)["IoU"] == 1.0 and labels.max() == 3
    assert (labels[gt == 0] == 0).all()
    far = cluster_depth(depth, K, gt > 0, DepthClusteringConfig(distance_m=0.06))  # links everything
    assert far.max() == 1

    from selfseg.baselines.simple import ForegroundComponents
    comps = ForegroundComponents().segment(None, 0, gt > 0)
    m = frame_metrics(comps, gt)  # boxes 1+2 merged (2800 px, box 1 = 1600 px matched), box 3 alone
    assert m["IoU"] == pytest.approx((1600 / 2800 + 0 + 1) / 3)


def test_git_info_is_the_code_as_loaded(tmp_path, monkeypatch):
    """A commit made while a run trains does not relabel its results: git_info answers what the process saw
    first (GIT_DIR points git at a throwaway repository)."""
    repo = tmp_path / "repo"
    repo.mkdir()

    def git(*args):
        return subprocess.run(["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t", *args],
                              check=True, capture_output=True, text=True).stdout.strip()
    git("init", "-q")
    (repo / "f.txt").write_text("1")
    git("add", "f.txt")
    git("commit", "-qm", "first")
    monkeypatch.setenv("GIT_DIR", str(repo / ".git"))
    monkeypatch.setenv("GIT_WORK_TREE", str(repo))
    git_info.cache_clear()
    try:
        seen = git_info()
        assert seen == {"commit": git("rev-parse", "HEAD"), "dirty": False}
        (repo / "f.txt").write_text("2")
        git("commit", "-qam", "second")
        assert git_info() == seen
        git_info.cache_clear()
        assert git_info()["commit"] == git("rev-parse", "HEAD") != seen["commit"]
    finally:
        git_info.cache_clear()


def test_cpu_model_tells_apart_cpu_types_of_one_name(tmp_path):
    """Two CPU types a virtual machine names alike (Zen 4 and Zen 5, both "AMD EPYC") get different model strings:
    the family and model numbers of the first processor are in them; without a model name the platform's answer."""
    def cpuinfo(family, model):
        cpu = (f"processor\t: {{n}}\nvendor_id\t: AuthenticAMD\ncpu family\t: {family}\nmodel\t\t: {model}\n"
               "model name\t: AMD EPYC\nflags\t\t: fpu avx2\n")
        f = tmp_path / f"cpuinfo-{family}-{model}"
        f.write_text(cpu.format(n=0) + "\n" + cpu.format(n=1).replace(f": {model}\n", ": 99\n"))
        return f
    zen4, zen5 = cpu_model(cpuinfo(25, 17)), cpu_model(cpuinfo(26, 2))
    assert zen4 == "AMD EPYC, family 25 model 17" and zen5 == "AMD EPYC, family 26 model 2"
    (tmp_path / "bare").write_text("processor\t: 0\n")
    assert cpu_model(tmp_path / "bare") not in (zen4, zen5, "")
