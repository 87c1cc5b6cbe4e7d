"""Baseline E (`picie`) and the shared semantic → instance machinery: loss, equivariance, k-means,
training foreground, determinism, resume, config errors, and the end-to-end run on tiny."""
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from selfseg.baselines.picie import (Geometric, PicieConfig, PicieNet, PicieNetConfig, apply_geometric, picie_loss,
                                     sample_geometric, train_picie)
from selfseg.baselines.semantic_instances import (Schedule, UnlabeledFrames, classes_to_instances,
                                                  spherical_kmeans, training_key)
from selfseg.dataset import Dataset
from selfseg.eval.cli import main as evaluate
from selfseg.method.background import BackgroundConfig, frame_foreground

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


class SyntheticFrames(UnlabeledFrames):
    """Frames of coloured rectangles on a grey table (labels: 0 = foreground, −1 = background), 48×64;
    ``crash_after``: the call to __getitem__ after that many raises (an interrupted run)."""

    def __init__(self, n: int = 6, crash_after: int | None = None):
        rng = np.random.default_rng(0)
        self.rgb, self.labels = [], []
        for _ in range(n):
            rgb = np.full((48, 64, 3), 110, np.uint8)
            lab = np.full((48, 64), -1, np.int32)
            for _ in range(3):
                y, x = rng.integers(4, 30), rng.integers(4, 44)
                rgb[y:y + 14, x:x + 16] = rng.integers(0, 256, 3)
                lab[y:y + 14, x:x + 16] = 0
            self.rgb.append(rgb)
            self.labels.append(lab)
        self.calls, self.crash_after = 0, crash_after

    def __getitem__(self, i: int):
        self.calls += 1
        if self.crash_after is not None and self.calls > self.crash_after:
            raise RuntimeError("simulated crash")
        return super().__getitem__(i)


def tiny_sched(**kw) -> Schedule:
    return Schedule(**{**dict(steps=6, batch_size=2, image_size=64, crop=(32, 48), checkpoint_every=2), **kw})


def tiny_picie(**kw) -> PicieConfig:
    return PicieConfig(**{**dict(net=PicieNetConfig(width=8, fpn_channels=8, embed_dim=8), train=tiny_sched(),
                                 cluster_every=3, n_classes=3, kmeans_iters=5, kmeans_pixels=2000), **kw})


def onehot_maps(ids: np.ndarray, dim: int) -> torch.Tensor:
    """B×H×W cluster ids → B×dim×H×W unit features sitting exactly on centroid e_id."""
    return torch.nn.functional.one_hot(torch.from_numpy(ids), dim).permute(0, 3, 1, 2).float()


def test_picie_loss_zero_for_consistent_views_and_known_value_otherwise():
    mu = torch.eye(4)[:3]  # K = 3 orthonormal centroids in 4-d, the same for both views
    ids = np.random.default_rng(0).integers(0, 3, (2, 5, 6))
    z1 = onehot_maps(ids, 4)
    fg = torch.ones(2, 5, 6, dtype=torch.bool)
    assert picie_loss(z1, z1.clone(), fg, mu, mu, tau=0.01).item() == pytest.approx(0.0, abs=1e-6)
    # A pixel whose view-2 feature sits on another centroid: both cross terms cost 1/τ = 100 nats.
    ids2 = ids.copy()
    flip = np.zeros_like(ids, bool)
    flip[0, :2] = True  # 12 of 60 pixels
    ids2[flip] = (ids[flip] + 1) % 3
    loss = picie_loss(z1, onehot_maps(ids2, 4), fg, mu, mu, tau=0.01).item()
    assert loss == pytest.approx(0.5 * 2 * 100 * 12 / 60, rel=1e-4)
    # ... unless those pixels are background: only foreground pixels count.
    assert picie_loss(z1, onehot_maps(ids2, 4), fg & ~torch.from_numpy(flip), mu, mu, 0.01).item() == \
        pytest.approx(0.0, abs=1e-6)
    assert picie_loss(z1, z1, torch.zeros_like(fg), mu, mu, 0.01).item() == 0.0


def test_equivariance_transform_commutes_with_pixelwise_segmentation():
    """G(segment(x)) == segment(G(x)) for a per-pixel classifier: exactly for labels (nearest),
    to rounding for features (bilinear is linear)."""
    rng = np.random.default_rng(1)
    x = torch.from_numpy(rng.random((3, 24, 32), dtype=np.float32))
    w = torch.from_numpy(rng.normal(size=(5, 3)).astype(np.float32))
    feats = lambda t: torch.einsum("kc,chw->khw", w, t)  # noqa: E731
    for _ in range(5):
        g = sample_geometric(24, 32, 0.4, True, rng)
        torch.testing.assert_close(apply_geometric(feats(x), g), feats(apply_geometric(x, g)), atol=1e-5, rtol=1e-5)
        seg_then_crop = apply_geometric(feats(x).argmax(0)[None].float(), g, "nearest")[0]
        crop_then_seg = feats(apply_geometric(x, g, "nearest")).argmax(0).float()
        assert torch.equal(seg_then_crop, crop_then_seg)
    # A known G: the right half, doubled in width by nearest resampling, then mirrored.
    ramp = torch.arange(8.0).repeat(2, 1)[None]  # 1×2×8, value = column
    out = apply_geometric(ramp, Geometric((0, 2, 4, 8), True), "nearest")[0, 0]
    assert out.tolist() == [7, 7, 6, 6, 5, 5, 4, 4]


def test_spherical_kmeans_finds_three_separated_directions():
    gen = torch.Generator().manual_seed(0)
    centres = torch.eye(3)
    x = torch.cat([c + 0.05 * torch.randn(200, 3, generator=gen) for c in centres])
    mu = spherical_kmeans(x, 3, 20, torch.Generator().manual_seed(1))
    assert sorted(mu.argmax(1).tolist()) == [0, 1, 2]
    assert (mu.max(1).values > 0.99).all()


def test_classes_become_connected_components_with_ours_min_size():
    classes = np.zeros((20, 30), np.int64)
    classes[:, 15:] = 1
    classes[2:8, 2:8] = 1  # class 1 again, not touching the right half: its own instance
    classes[10:12, 20:22] = 0  # 4 px of class 0 inside class 1: absorbed by its neighbour
    fg = np.ones((20, 30), bool)
    fg[:, 28:] = False
    inst = classes_to_instances(classes, fg, connectivity=8, min_px=10)
    assert inst[:, 28:].max() == 0
    assert len(np.unique(inst[fg])) == 3
    assert inst[11, 21] == inst[0, 20] != inst[3, 3] != inst[19, 0]


def test_instance_settings_reuse_the_trained_network():
    base = training_key(PicieConfig())
    assert training_key(PicieConfig(instances="classes", min_component_px=5, connectivity=4, device="cpu")) == base
    assert training_key(PicieConfig(n_classes=5)) != base


def test_training_foreground_comes_from_depth_above_the_support_plane(analytic_dataset):
    ds = Dataset(analytic_dataset)
    for vid in ds.video_ids:
        v = ds.video(vid)
        fg = frame_foreground(v.depth_m(0), v.K(0), BackgroundConfig())
        gt = ds.labeled(vid).inst(0) > 0
        assert (fg & gt).sum() / (fg | gt).sum() > 0.8


def test_picie_net_shapes():
    net = PicieNet(PicieNetConfig(width=8, fpn_channels=8, embed_dim=6)).eval()
    with torch.no_grad():
        z = net(torch.rand(2, 3, 37, 50))
    assert z.shape == (2, 6, 37, 50)
    torch.testing.assert_close(z.norm(dim=1), torch.ones(2, 37, 50))


def test_picie_training_is_deterministic_and_resumes_exactly(tmp_path):
    cfg = tiny_picie()
    net_a, mu_a = train_picie(SyntheticFrames(), cfg, tmp_path / "a", progress=False)
    net_b, mu_b = train_picie(SyntheticFrames(), cfg, tmp_path / "b", progress=False)
    # Calls: step 0 clusters 6 frames + a batch of 2 (8), steps 1–2: 12, step 3 clusters again: 20;
    # the step-4 checkpoint is written after step 3, so the 21st call (in step 4) crashes after it.
    with pytest.raises(RuntimeError, match="simulated crash"):
        train_picie(SyntheticFrames(crash_after=20), cfg, tmp_path / "c", progress=False)
    assert [p.name for p in (tmp_path / "c" / "checkpoints").iterdir()] == ["step_000004.pt"]
    net_c, mu_c = train_picie(SyntheticFrames(), cfg, tmp_path / "c", progress=False)
    for other, mu in ((net_b, mu_b), (net_c, mu_c)):
        sa, sb = net_a.state_dict(), other.state_dict()
        assert all(torch.equal(sa[k], sb[k]) for k in sa)
        assert torch.equal(mu_a, mu)
    log = json.loads((tmp_path / "c" / "training_log.json").read_text())
    assert log["loss"] == json.loads((tmp_path / "a" / "training_log.json").read_text())["loss"]
    assert not (tmp_path / "c" / "checkpoints").exists()  # the final weights replace them
    # A finished run is loaded, not retrained; other settings are refused.
    assert torch.equal(train_picie(SyntheticFrames(crash_after=0), cfg, tmp_path / "a", progress=False)[1], mu_a)
    with pytest.raises(ValueError, match="other settings"):
        train_picie(SyntheticFrames(), tiny_picie(tau=0.5), tmp_path / "a", progress=False)


@pytest.mark.parametrize("speed", [{"channels_last": True}, {"channels_last": True, "precision": "bf16"}])
def test_speed_settings_train_picie_the_same_run_to_rounding_and_resume_bitwise(tmp_path, speed):
    """As the embedding trainer's speed settings: step 0's loss equals float32's to rounding (channels_last sums
    in another order; bf16 keeps 8 bits of mantissa), the run differs, and it resumes bitwise."""
    train_picie(SyntheticFrames(), tiny_picie(), tmp_path / "fp32", progress=False)
    cfg = tiny_picie(train=tiny_sched(**speed))
    _, mu = train_picie(SyntheticFrames(), cfg, tmp_path / "fast", progress=False)
    log, ref = (json.loads((tmp_path / d / "training_log.json").read_text())["loss"] for d in ("fast", "fp32"))
    assert log[0] == pytest.approx(ref[0], rel=1e-2 if "precision" in speed else 1e-5) and log != ref
    with pytest.raises(RuntimeError, match="simulated crash"):
        train_picie(SyntheticFrames(crash_after=20), cfg, tmp_path / "resumed", progress=False)
    _, mu_res = train_picie(SyntheticFrames(), cfg, tmp_path / "resumed", progress=False)
    assert mu.dtype == torch.float32 and torch.equal(mu, mu_res)
    assert json.loads((tmp_path / "resumed" / "training_log.json").read_text())["loss"] == log
    with pytest.raises(ValueError, match="precision"):
        tiny_sched(precision="fp16")


@pytest.mark.parametrize("override, word", [("n_classes=0", "n_classes"), ("n_classes=-3", "n_classes"),
                                            ("train.steps=0", "steps"), ("cluster_every=0", "cluster_every"),
                                            ("train.crop=[8,8]", "crop")])
def test_bad_k_or_schedule_is_a_one_line_error(tmp_path, capsys, override, word):
    for method in ("picie", "stego"):
        if method == "stego" and override.startswith("cluster_every"):
            continue
        assert evaluate(["--method", method, "--data", str(tmp_path), "--set", override]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and word in err


@pytest.fixture(scope="module")
def tiny(tiny_dataset) -> Path:
    """conftest's session-wide generated tiny preset."""
    return tiny_dataset


def tiny_scores(results: Path, name: str) -> dict:
    return json.loads((results / "scores" / "tiny" / name / "fold0.json").read_text())["metrics"]


@pytest.mark.slow
def test_picie_end_to_end_on_tiny(tiny, tmp_path):
    assert evaluate(["--method", "picie", "--data", str(tiny), "--out", str(tmp_path), "--folds", "0", "--quiet",
                     "--config", str(CONFIGS / "picie-tiny.yaml"), "--set", "train.steps=40",
                     "--set", "cluster_every=20"]) == 0
    m = tiny_scores(tmp_path, "picie")
    print({k: round(m[k], 3) for k in ("P", "R", "IoU")})
    assert m["n_frames"] > 0
    assert m["IoU"] > 0.3 and m["P"] > 0.5  # a class map split into components; one-segment scores ~.1
