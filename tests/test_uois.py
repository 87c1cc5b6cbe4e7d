"""Baseline B (`uois-sim`): centre voting on analytic boxes, DSN targets, mask perturbation, the refusal of
missing or overlapping training data, and the end-to-end run on tiny with a disjoint training set."""
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from selfseg.baselines.sim_data import GTFrames, open_disjoint_train_data
from selfseg.baselines.uois import RefineNet, UoisConfig, centre_targets, cluster_votes, perturb_mask, rrn_batch
from selfseg.dataset import Dataset, DatasetError
from selfseg.eval.cli import main as evaluate
from selfseg.fileio import write_json
from selfseg.generate.cli import main as generate_scenes
from selfseg.raycast import xyz_map

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
TINY_POOL_DISJOINT = "cube,book,jar,egg,can_soup,chips_tube,flowerpot,hex_box"  # none of tiny's objects


def test_centre_voting_recovers_the_box_centres_from_perfect_offsets(analytic_dataset):
    ds = Dataset(analytic_dataset)
    video = ds.labeled(ds.video_ids[0])
    f = video.frame_ids[0]
    xyz, inst = xyz_map(video.depth_m(f), video.K(f)), video.inst(f).astype(np.int32)
    off, valid = centre_targets(xyz, inst)
    ids = np.unique(inst[valid])
    assert len(ids) >= 2
    truth = np.array([xyz[valid & (inst == k)].mean(0) for k in ids])  # the visible-surface centres
    rng = np.random.default_rng(0)
    votes = xyz[valid] + off[valid] + rng.normal(0, 0.002, (valid.sum(), 3))  # 2 mm vote noise
    labels, centres = cluster_votes(votes, sigma_m=0.02, n_seeds=50, iters=10, merge_m=0.03, max_points=3000)
    assert len(centres) == len(ids)
    for k, c in zip(ids, truth):
        mine = labels[inst[valid] == k]
        assert np.all(mine == mine[0])  # one cluster per box, and no two boxes share one
        np.testing.assert_allclose(centres[mine[0]], c, atol=1e-3)
    assert len({labels[inst[valid] == k][0] for k in ids}) == len(ids)


def test_centre_targets_point_every_object_pixel_at_its_instance_mean():
    xyz = np.zeros((4, 6, 3), np.float32)
    xyz[..., 2] = 1.0
    xyz[:, :3, 0] = np.arange(3)[None]
    xyz[:, 3:, 0] = 10 + np.arange(3)[None]
    inst = np.zeros((4, 6), np.int32)
    inst[:, :3], inst[:, 3:5] = 1, 2
    off, valid = centre_targets(xyz, inst)
    np.testing.assert_allclose((xyz + off)[:, :3], np.broadcast_to([1.0, 0, 1], (4, 3, 3)))
    np.testing.assert_allclose((xyz + off)[:, 3:5], np.broadcast_to([10.5, 0, 1], (4, 2, 3)))
    assert not valid[:, 5].any() and np.all(off[:, 5] == 0)


def test_perturbed_masks_differ_but_overlap_and_rrn_batches_are_deterministic(analytic_dataset):
    mask = np.zeros((60, 80), bool)
    mask[20:40, 25:55] = True
    rng = np.random.default_rng(3)
    for _ in range(10):
        bad = perturb_mask(mask, rng)
        iou = (bad & mask).sum() / (bad | mask).sum()
        assert 0.3 < iou < 1.0
    frames = GTFrames(Dataset(analytic_dataset), frame_stride=2)
    cfg = UoisConfig(rrn_size=32)
    x1, t1 = rrn_batch(frames, cfg, 7)
    x2, t2 = rrn_batch(frames, cfg, 7)
    assert x1.shape == (16, 4, 32, 32) and t1.shape == (16, 32, 32)
    assert torch.equal(x1, x2) and torch.equal(t1, t2) and not torch.equal(x1, rrn_batch(frames, cfg, 8)[0])
    assert RefineNet(8)(x1[:2]).shape == (2, 32, 32)


def fake_dataset(root: Path, objects: list[str]) -> Path:
    """The smallest folder ``Dataset`` opens, with the given object names."""
    write_json(root / "dataset_info.json", {"format_version": 1, "name": root.name, "resolution": [160, 120],
                                            "objects": [{"obj_id": i + 1, "name": n} for i, n in enumerate(objects)]})
    write_json(root / "videos" / "000000" / "scene_camera.json", {})
    return root


@pytest.mark.parametrize("method, overlapping", [("uois-sim", False), ("sdmaskrcnn-sim", True)])
def test_missing_or_overlapping_training_data_is_a_one_line_error(analytic_dataset, tmp_path, capsys, method,
                                                                  overlapping):
    extra = []
    if overlapping:
        objects = sorted(o["name"] for o in Dataset(analytic_dataset).info["objects"])
        extra = ["--set", f"train_data={fake_dataset(tmp_path / 'overlap', ['cube', objects[0]])}"]
    assert evaluate(["--method", method, "--data", str(analytic_dataset), "--out", str(tmp_path / "r"),
                     "--folds", "0", "--quiet", *extra]) == 2
    err = capsys.readouterr().err.strip()
    words = "shares objects with the test dataset" if overlapping else "needs train_data"
    assert len(err.splitlines()) == 1 and words in err, err


def test_training_data_checks(analytic_dataset, tmp_path):
    objects = sorted(o["name"] for o in Dataset(analytic_dataset).info["objects"])
    for path, words in [("", "needs train_data"), (str(tmp_path / "nowhere"), "not found"),
                        (str(analytic_dataset), "test dataset itself"),
                        (str(fake_dataset(tmp_path / "overlap", ["cube", objects[1]])), f"objects .*: {objects[1]};")]:
        with pytest.raises(DatasetError, match=words):
            open_disjoint_train_data(path, analytic_dataset, "uois-sim")
    ok = fake_dataset(tmp_path / "other", ["cube", "egg"])
    assert open_disjoint_train_data(str(ok), analytic_dataset, "uois-sim").root == ok


@pytest.fixture(scope="module")
def tiny(tiny_dataset) -> Path:
    """conftest's session-wide generated tiny preset."""
    return tiny_dataset


@pytest.fixture(scope="module")
def tiny_disjoint(tmp_path_factory) -> Path:
    """A small training set of objects tiny never uses (2 videos × 12 frames, Workbench)."""
    out = tmp_path_factory.getbasetemp() / "tiny-disjoint-workbench" / "data"
    assert generate_scenes(["--preset", "tiny", "--object-pool", TINY_POOL_DISJOINT, "--scenes", "2", "--frames", "12",
                            "--renderer", "workbench", "--out", str(out), "--quiet"]) == 0
    return out


def fold0(results: Path, name: str) -> dict:
    return json.loads((results / "scores" / "tiny" / name / "fold0.json").read_text())


@pytest.mark.slow
def test_uois_end_to_end_on_tiny(tiny, tiny_disjoint, tmp_path, monkeypatch):
    monkeypatch.chdir(tiny_disjoint.parent.parent)  # train_data relative to the working directory, as in the demo
    relative = tiny_disjoint.relative_to(tiny_disjoint.parent.parent)
    assert evaluate(["--method", "uois-sim", "--data", str(tiny), "--out", str(tmp_path), "--folds", "0", "--quiet",
                     "--config", str(CONFIGS / "uois-sim-tiny.yaml"), "--set", f"train_data={relative}",
                     "--set", "frame_stride=2", "--set", "dsn_train.steps=40", "--set", "rrn_train.steps=30"]) == 0
    rec = fold0(tmp_path, "uois-sim")
    m = rec["metrics"]
    print({k: round(m[k], 3) for k in ("P", "R", "IoU")})
    assert rec["train_data"]["content_hash"] == Dataset(tiny_disjoint).content_hash()
    assert rec["train_data"]["root"] == str(tiny_disjoint.resolve())
    assert m["n_frames"] > 0
    assert m["IoU"] > 0.15  # one-segment scores ~.1 on tiny


def test_fit_is_deterministic_whatever_the_global_rng_and_reuses_trained_weights(analytic_dataset, tmp_path):
    from types import SimpleNamespace

    from selfseg.baselines.maskrcnn import MaskRCNNNetConfig, SDMaskRCNNConfig, SDMaskRCNNSim
    from selfseg.baselines.sim_data import SimSchedule
    from selfseg.baselines.uois import UoisSim
    from selfseg.method.network import NetConfig

    test_videos = [SimpleNamespace(root=fake_dataset(tmp_path / "test", ["cube", "egg"]))]
    short = SimSchedule(steps=2, batch_size=2, threads=1)
    configs = {UoisSim: UoisConfig(train_data=str(analytic_dataset), dsn_train=short, rrn_train=short, rrn_width=4,
                                   rrn_size=32, dsn_net=NetConfig(width=8, aspp_channels=8, low_level_channels=8,
                                                                  decoder_channels=8, embed_dim=4)),
               SDMaskRCNNSim: SDMaskRCNNConfig(train_data=str(analytic_dataset), train=short, net=MaskRCNNNetConfig(
                   width=8, fpn_channels=8, box_fc=16, mask_channels=8))}
    for cls, cfg in configs.items():
        states = []
        for run in range(2):
            torch.manual_seed(run)  # the global RNG differs between the runs
            m = cls(cfg, tmp_path / f"{cls.name}{run}" / "fold0")
            m.fit(test_videos)
            states.append({k: v.clone() for k, v in (m.dsn if cls is UoisSim else m.model).state_dict().items()})
            assert m.train_data["content_hash"] == Dataset(analytic_dataset).content_hash()
        assert all(torch.equal(states[0][k], states[1][k]) for k in states[0])
        again = cls(cfg, tmp_path / f"{cls.name}0" / "fold1")  # another fold of the same run: trained weights reused
        again.fit(test_videos)
        net = again.dsn if cls is UoisSim else again.model
        assert all(torch.equal(states[0][k], v) for k, v in net.state_dict().items())
