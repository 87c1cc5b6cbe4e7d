"""Baseline F (`stego`): DINO's loss and centre, STEGO's correlation loss against slow loops,
patch masks, the ViT, determinism and resume of both phases, and the end-to-end run on tiny."""
import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from selfseg.baselines.stego import (DINO_DIR, DinoConfig, StegoConfig, StegoHeadConfig, ViT, ViTConfig,
                                     dino_loss, patch_foreground, stego_corr_loss, train_dino, train_stego,
                                     update_center)
from selfseg.eval.cli import main as evaluate
from test_picie import CONFIGS, SyntheticFrames, tiny, tiny_sched, tiny_scores  # noqa: F401  (tiny: fixture)


def test_dino_loss_matches_a_slow_loop():
    gen = torch.Generator().manual_seed(0)
    V, G, B, O = 5, 2, 3, 7  # noqa: E741
    student, teacher = torch.randn(V, B, O, generator=gen), torch.randn(G, B, O, generator=gen)
    center = torch.randn(O, generator=gen)
    ts, tt = 0.1, 0.04
    total, pairs = 0.0, 0
    for g in range(G):
        for v in range(V):
            if v == g:
                continue
            for b in range(B):
                z = [math.exp((teacher[g, b, o].item() - center[o].item()) / tt) for o in range(O)]
                zs = [math.exp(student[v, b, o].item() / ts) for o in range(O)]
                total += -sum(z[o] / sum(z) * math.log(zs[o] / sum(zs)) for o in range(O)) / B
            pairs += 1
    assert dino_loss(student, teacher, center, ts, tt).item() == pytest.approx(total / pairs, rel=1e-5)
    # Centring: EMA of the teacher's mean over crops and batch.
    new = update_center(center, teacher, 0.9)
    for o in range(O):
        mean = sum(teacher[g, b, o].item() for g in range(G) for b in range(B)) / (G * B)
        assert new[o].item() == pytest.approx(0.9 * center[o].item() + 0.1 * mean, rel=1e-5, abs=1e-6)


def test_dino_loss_gradient_reaches_the_student_only():
    s = torch.randn(3, 2, 4, requires_grad=True)
    t = torch.randn(2, 2, 4, requires_grad=True)
    dino_loss(s, t, torch.zeros(4), 0.1, 0.04).backward()
    assert s.grad is not None and s.grad.abs().sum() > 0 and t.grad is None


def slow_corr_loss(f1, f2, c1, c2, m1, m2, shift) -> float:
    """STEGO's correlation loss written out pixel pair by pixel pair."""
    B, _, h, w = f1.shape
    cos = lambda a, b: float(a @ b / (a.norm() * b.norm()))  # noqa: E731
    pix = [(y, x) for y in range(h) for x in range(w)]
    pairs = [(b, p, q) for b in range(B) for p in pix for q in pix if m1[b][p] and m2[b][q]]
    fd = {(b, p, q): cos(f1[b, :, p[0], p[1]], f2[b, :, q[0], q[1]]) for b, p, q in pairs}
    old_mean = sum(fd.values()) / len(pairs)
    row = {}
    for b, p, q in pairs:
        row.setdefault((b, p), []).append(fd[(b, p, q)])
    centred = {k: v - np.mean(row[(k[0], k[1])]) for k, v in fd.items()}
    centred_mean = sum(centred.values()) / len(pairs)
    total = 0.0
    for b, p, q in pairs:
        s = cos(c1[b, :, p[0], p[1]], c2[b, :, q[0], q[1]])
        total += -(centred[(b, p, q)] - centred_mean + old_mean - shift) * max(s, 0.0)
    return total / len(pairs)


def test_stego_correlation_loss_matches_a_slow_loop():
    gen = torch.Generator().manual_seed(3)
    B, C, D, h, w = 2, 5, 4, 3, 4
    f1, f2 = torch.randn(B, C, h, w, generator=gen), torch.randn(B, C, h, w, generator=gen)
    c1, c2 = torch.randn(B, D, h, w, generator=gen), torch.randn(B, D, h, w, generator=gen)
    m1, m2 = torch.rand(B, h, w, generator=gen) > 0.3, torch.rand(B, h, w, generator=gen) > 0.3
    for shift in (0.0, 0.18, 0.46):
        fast = stego_corr_loss(f1, f2, c1, c2, m1, m2, shift).item()
        assert fast == pytest.approx(slow_corr_loss(f1, f2, c1, c2, m1.numpy(), m2.numpy(), shift), rel=1e-4, abs=1e-6)
    assert stego_corr_loss(f1, f2, c1, c2, m1, torch.zeros_like(m2), 0.1).item() == 0.0
    # The self term pulls codes together where features agree: it is lowest when codes equal features.
    f = torch.randn(1, 4, 3, 3, generator=gen)
    m = torch.ones(1, 3, 3, dtype=torch.bool)
    aligned = stego_corr_loss(f, f, f, f, m, m, 0.0)
    scrambled = stego_corr_loss(f, f, f.flip(1), f.roll(1, 2), m, m, 0.0)
    assert aligned < scrambled


def test_patch_foreground_and_vit_padding():
    fg = torch.zeros(1, 10, 17, dtype=torch.bool)
    fg[0, :8, :8] = True  # patch (0, 0) full
    fg[0, :4, 8:16] = True  # patch (0, 1) half
    pm = patch_foreground(fg, 8, 0.5)
    assert pm.shape == (1, 2, 3)
    assert pm[0].tolist() == [[True, True, False], [False, False, False]]
    assert patch_foreground(fg, 8, 0.75)[0, 0].tolist() == [True, False, False]
    vit = ViT(ViTConfig(dim=16, depth=1, heads=2)).eval()
    with torch.no_grad():
        cls, patches = vit(torch.rand(2, 3, 10, 17))
    assert cls.shape == (2, 16) and patches.shape == (2, 16, 2, 3)


def tiny_stego(**kw) -> StegoConfig:
    return StegoConfig(**{**dict(vit=ViTConfig(dim=16, depth=1, heads=2, pos_grid=6),
                                 dino=DinoConfig(train=tiny_sched(), out_dim=16, global_px=16, local_crops=1,
                                                 local_px=8),
                                 head=StegoHeadConfig(embed_dim=4), train=tiny_sched(steps=4), n_classes=3, knn=2,
                                 kmeans_iters=5, kmeans_pixels=2000), **kw})


def test_dino_is_deterministic_and_resumes_exactly(tmp_path):
    cfg = tiny_stego()
    vit_a, _ = train_dino(SyntheticFrames(), cfg, tmp_path / "a", progress=False)
    vit_b, _ = train_dino(SyntheticFrames(), cfg, tmp_path / "b", progress=False)
    # 2 frames per step: the 9th call (step index 4) crashes after the checkpoint written at 4 steps.
    with pytest.raises(RuntimeError, match="simulated crash"):
        train_dino(SyntheticFrames(crash_after=8), cfg, tmp_path / "c", progress=False)
    assert [p.name for p in (tmp_path / "c" / "checkpoints").iterdir()] == ["step_000004.pt"]
    vit_c, _ = train_dino(SyntheticFrames(), cfg, tmp_path / "c", progress=False)
    for other in (vit_b, vit_c):
        sa, sb = vit_a.state_dict(), other.state_dict()
        assert all(torch.equal(sa[k], sb[k]) for k in sa)
    # The EMA teacher moved away from its initialisation.
    torch.manual_seed(cfg.dino.train.seed)
    init = ViT(cfg.vit).state_dict()
    assert not torch.equal(init["embed.weight"], vit_a.state_dict()["embed.weight"])


def test_stego_head_is_deterministic_and_segments_unit_codes(tmp_path):
    cfg = tiny_stego()
    net_a, mu_a = train_stego(SyntheticFrames(), cfg, tmp_path / "a", progress=False)
    net_b, mu_b = train_stego(SyntheticFrames(), cfg, tmp_path / "b", progress=False)
    assert torch.equal(mu_a, mu_b) and mu_a.shape == (3, 4)
    sa, sb = net_a.head.state_dict(), net_b.head.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    with torch.no_grad():
        codes = net_a(torch.rand(1, 3, 21, 30))
    assert codes.shape == (1, 4, 21, 30)
    torch.testing.assert_close(codes.norm(dim=1), torch.ones(1, 21, 30))
    # A finished run is loaded without touching the frames.
    assert torch.equal(train_stego(SyntheticFrames(crash_after=0), cfg, tmp_path / "a", progress=False)[1], mu_a)


def test_bf16_trains_dino_and_the_head_the_same_run_to_rounding_and_resumes_bitwise(tmp_path):
    """Both phases under bf16 autocast: each phase's first loss equals float32's to rounding, the runs differ,
    and DINO resumes bitwise."""
    train_stego(SyntheticFrames(), tiny_stego(), tmp_path / "fp32", progress=False)
    fast = tiny_stego(dino=dataclasses.replace(tiny_stego().dino, train=tiny_sched(precision="bf16")),
                      train=tiny_sched(steps=4, precision="bf16"))
    _, mu = train_stego(SyntheticFrames(), fast, tmp_path / "bf16", progress=False)
    for phase in (DINO_DIR, "."):
        log, ref = (json.loads((tmp_path / d / phase / "training_log.json").read_text())["loss"]
                    for d in ("bf16", "fp32"))
        assert log[0] == pytest.approx(ref[0], rel=2e-2) and log != ref, phase
    assert mu.dtype == torch.float32
    with pytest.raises(RuntimeError, match="simulated crash"):
        train_dino(SyntheticFrames(crash_after=8), fast, tmp_path / "resumed", progress=False)
    vit_res, _ = train_dino(SyntheticFrames(), fast, tmp_path / "resumed", progress=False)
    vit, _ = train_dino(SyntheticFrames(crash_after=0), fast, tmp_path / "bf16" / DINO_DIR, progress=False)
    sa, sb = vit.state_dict(), vit_res.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)


@pytest.mark.slow
def test_stego_end_to_end_on_tiny(tiny, tmp_path):  # noqa: F811
    assert evaluate(["--method", "stego", "--data", str(tiny), "--out", str(tmp_path), "--folds", "0", "--quiet",
                     "--config", str(CONFIGS / "stego-tiny.yaml"), "--set", "dino.train.steps=40",
                     "--set", "train.steps=30"]) == 0
    m = tiny_scores(tmp_path, "stego")
    print({k: round(m[k], 3) for k in ("P", "R", "IoU")})
    assert m["n_frames"] > 0
    assert m["IoU"] > 0.3 and m["P"] > 0.5  # a class map split into components; one-segment scores ~.1

