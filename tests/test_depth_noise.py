"""The depth-noise model (generate/depth_noise.py) against analytic scenes: planes at known distances and angles
and a box in front of a wall, seen by the 320×240 camera of the calibrated presets; and generation with the
noise on, whose ground truth must equal generation without it.

Statistical tolerances: each frame has 76,800 pixels, so counts are checked within 5 binomial standard errors
and standard deviations within 3 % (5 standard errors of a sample std are about 1.3 %).
"""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from scipy import ndimage

from selfseg.generate.cli import main, recorded_config
from selfseg.generate.depth_noise import (DepthNoiseConfig, add_depth_noise, axial_sigma_m, edge_mask, frame_rng,
                                          grazing_probability, incidence_cos, projector_shadow, to_disparity)
from selfseg.generate.presets import preset_config
from selfseg.generate.render import intrinsics

W, H = 320, 240
K = intrinsics(W, H, 58.0)
FX = K[0, 0]
CFG = DepthNoiseConfig()
FB = CFG.sensor_focal_px * CFG.baseline_m  # sensor focal × baseline (px·m)


def _phi(x: float) -> float:
    return 0.5 * (1.0 + math.erf(x / math.sqrt(2.0)))


def _rays() -> np.ndarray:
    """Per pixel the ray (x/z, y/z, 1) in the camera frame, 3×H×W."""
    x = (np.arange(W)[None, :] - K[0, 2]) / FX + np.zeros((H, 1))
    y = (np.arange(H)[:, None] - K[1, 2]) / K[1, 1] + np.zeros((1, W))
    return np.stack([x, y, np.ones((H, W))])


def _plane(tilt_deg: float, z0_m: float, far_m: float = 6.0) -> tuple[np.ndarray, np.ndarray]:
    """Planar depth (m) of the plane through (0, 0, z0) whose normal is tilted by ``tilt_deg`` about the camera's
    y axis (depth grows to the right; 0 where the plane is behind the camera or beyond ``far_m``), and the true
    cos of each pixel's incidence angle."""
    t = math.radians(tilt_deg)
    n = np.array([math.sin(t), 0.0, -math.cos(t)])
    rays = _rays()
    dot = n[0] * rays[0] + n[2] * rays[2]
    with np.errstate(divide="ignore"):
        z = n[2] * z0_m / dot
    z = np.where((z > 0) & (z < far_m), z, 0.0)
    cos_true = np.abs(dot) / np.sqrt((rays ** 2).sum(0))
    return z, cos_true


def _noisy(depth: np.ndarray, cfg: DepthNoiseConfig = CFG, seed: int = 1, frame: int = 0) -> np.ndarray:
    return add_depth_noise(depth, K, cfg, frame_rng(seed, frame)).astype(np.float64)


def _quantised_gaussian_levels(z_m: float) -> dict[int, float]:
    """Probability of each disparity level k (disparity k·step) for a true depth z: N(f·b/z, σ²) rounded."""
    d0, s, sig = FB / z_m, CFG.disparity_step_px, CFG.disparity_sigma_px
    k0 = round(d0 / s)
    return {k: _phi(((k + 0.5) * s - d0) / sig) - _phi(((k - 0.5) * s - d0) / sig) for k in range(k0 - 8, k0 + 9)}


@pytest.mark.parametrize("z_m", [0.6, 1.0, 1.7, 2.5])
def test_fronto_parallel_plane_is_a_quantised_gaussian_in_disparity(z_m):
    out = _noisy(np.full((H, W), z_m))
    assert (out > 0).all()  # nothing to drop: no edge, incidence ≤ 35°, the projector lights everything
    k = FB / out / CFG.disparity_step_px
    assert np.abs(k - np.rint(k)).max() < 1e-3  # only the 1/8-px disparity levels
    k = np.rint(k).astype(int)
    probs = _quantised_gaussian_levels(z_m)
    n = out.size
    for level, p in probs.items():
        assert abs((k == level).sum() - n * p) <= 5 * math.sqrt(n * p * (1 - p)) + 1, (level, p)
    assert set(np.unique(k)) <= set(probs)
    levels = np.array([FB / (lv * CFG.disparity_step_px) for lv in probs])
    p = np.array(list(probs.values()))
    mean = (p * levels).sum()
    predicted_std = math.sqrt((p * (levels - mean) ** 2).sum())
    assert out.std() == pytest.approx(predicted_std, rel=0.03)
    # the depth error grows with the square of the distance: z²/(f·b)·√(σ² + step²/12) within the phase's effect
    assert predicted_std == pytest.approx(z_m ** 2 / FB * math.hypot(CFG.disparity_sigma_px,
                                                                      CFG.disparity_step_px / math.sqrt(12)), rel=0.35)


def test_tilted_plane_adds_the_lateral_jitter_to_the_disparity_noise():
    """On a plane tilted by 60° the disparity is affine in the pixel, so a shift by (Δu, Δv) changes it by g_u Δu:
    var(d_measured − d_true) = g_u² var(Δu) + σ² + step²/12 (the pixels' rounding phases are spread evenly)."""
    z, _ = _plane(60.0, 1.0)
    out = _noisy(z)
    d_true = to_disparity(z, CFG.sensor_focal_px, CFG.baseline_m)
    g_u = FB * math.tan(math.radians(60.0)) / (1.0 * FX)  # ∂d/∂u, sensor px per image px
    assert np.diff(d_true[:, 40:200], axis=1) == pytest.approx(-g_u, rel=1e-9)
    sigma_shift = CFG.lateral_sigma_px * FX / CFG.sensor_focal_px  # image px
    var_shift = sum(k * k * (_phi((k + 0.5) / sigma_shift) - _phi((k - 0.5) / sigma_shift)) for k in range(-6, 7))
    disparity_var = CFG.disparity_sigma_px ** 2 + CFG.disparity_step_px ** 2 / 12
    inner = np.zeros((H, W), bool)
    inner[5:-5, 5:200] = True  # away from the clamped border and from grazing incidence (θ ≤ 70° there)
    assert (out[inner] > 0).all()
    resid = FB / out[inner] - d_true[inner]
    assert resid.std() == pytest.approx(math.sqrt(g_u ** 2 * var_shift + disparity_var), rel=0.03)
    assert abs(resid.mean()) < 5 * resid.std() / math.sqrt(resid.size)
    assert resid.std() > 1.15 * math.sqrt(disparity_var)  # the lateral term is measurable here


@pytest.mark.parametrize("z_m", [0.8, 1.5, 2.5])
def test_axial_noise_follows_nguyen_et_al(z_m):
    cfg = dataclasses.replace(CFG, axial=True, disparity_sigma_px=0.0, disparity_step_px=0.0)
    out = _noisy(np.full((H, W), z_m), cfg)
    sigma = 0.0012 + 0.0019 * (z_m - 0.4) ** 2
    assert float(axial_sigma_m(np.array(z_m), cfg)) == pytest.approx(sigma)
    assert out.std() == pytest.approx(sigma, rel=0.03)
    assert abs(out.mean() - z_m) < 5 * sigma / math.sqrt(out.size) + 1e-6  # + float32's rounding of the output


@pytest.mark.parametrize("tilt_deg", [50.0, 65.0, 75.0, 82.0])
def test_grazing_dropout_fraction_follows_the_incidence_angle(tilt_deg):
    z, cos_true = _plane(tilt_deg, 1.0)
    valid = z > 0
    est = incidence_cos(z, K)
    interior = ndimage.binary_erosion(valid, np.ones((3, 3), bool))
    assert np.abs(est - cos_true)[interior].max() < 1e-9  # normals from the depth map are exact on a plane
    cfg = dataclasses.replace(CFG, edge_dropout=0.0, lateral_sigma_px=0.0)  # only the grazing dropout
    dropped = (_noisy(z, cfg) == 0) & valid
    p = grazing_probability(cos_true, CFG.grazing_start_deg, CFG.grazing_full_deg)[valid]
    theta = np.degrees(np.arccos(cos_true[valid]))
    d = dropped[valid]
    assert not d[theta < CFG.grazing_start_deg - 0.01].any()
    assert d[theta > CFG.grazing_full_deg + 0.01].all()
    expected, se = p.sum(), math.sqrt((p * (1 - p)).sum())
    assert abs(d.sum() - expected) <= 5 * se + 1
    lo, hi = (p > 0) & (p < 0.3), (p > 0.7) & (p < 1)
    if min(lo.sum(), hi.sum()) > 500:  # within the ramp the dropout rises with the angle
        assert d[lo].mean() < 0.35 and d[hi].mean() > 0.65


def test_a_box_in_front_of_a_wall_drops_its_projector_shadow_and_an_edge_band():
    z1, z2 = 0.8, 1.0
    box = np.zeros((H, W), bool)
    box[60:180, 120:200] = True
    depth = np.where(box, z1, z2)
    # the projector (7.5 cm along +x) casts the box's shadow on the wall to its left, fx·b·(1/z1 − 1/z2) px wide
    shadow = projector_shadow(depth, FX, CFG.baseline_m)
    width = FX * CFG.baseline_m * (1 / z1 - 1 / z2)
    expected = np.zeros((H, W), bool)
    expected[60:180, math.floor(120 - width) + 1:120] = True
    assert width == pytest.approx(5.41, abs=0.01) and (shadow == expected).all()
    # pixels within the edge radius (image px) of a pixel across the box's outline
    radius = math.floor(CFG.edge_radius_px * FX / CFG.sensor_focal_px + 0.5)
    across = np.where(box, ndimage.distance_transform_cdt(box, "chessboard"),
                      ndimage.distance_transform_cdt(~box, "chessboard"))
    band = edge_mask(to_disparity(depth, CFG.sensor_focal_px, CFG.baseline_m), CFG.edge_jump_px, radius)
    assert radius == 2 and (band <= (across <= radius + 1)).all() and (band >= (across <= radius)).all()
    assert (band != (across <= radius + 1)).sum() == 4  # the diagonal pixel beyond each outer corner
    out = _noisy(depth)
    dropped = out == 0
    assert dropped[shadow].all()
    assert not dropped[~band & ~shadow].any()  # fronto-parallel: no grazing dropout
    edge_only = band & ~shadow
    n, k = edge_only.sum(), dropped[edge_only].sum()
    assert abs(k - n * CFG.edge_dropout) <= 5 * math.sqrt(n * CFG.edge_dropout * (1 - CFG.edge_dropout))
    # no edge band, no shadow: nothing drops
    assert (_noisy(depth, dataclasses.replace(CFG, edge_dropout=0.0, projector_shadow=False)) > 0).all()


def test_noise_is_a_function_of_scene_seed_and_frame():
    z, _ = _plane(40.0, 0.9)
    a = _noisy(z, seed=7, frame=3)
    assert np.array_equal(a, _noisy(z, seed=7, frame=3))
    assert not np.array_equal(a, _noisy(z, seed=7, frame=4))
    assert not np.array_equal(a, _noisy(z, seed=8, frame=3))
    assert (a[z == 0] == 0).all()  # no surface, no measurement


def test_presets_and_the_recorded_config():
    calibrated, cluttered = preset_config("calibrated"), preset_config("cluttered")
    assert (cluttered.library, cluttered.objects_per_scene, cluttered.physics.layout) == ("paper", 12, "pile")
    assert (cluttered.scenes, cluttered.frames, cluttered.width, cluttered.height) == (12, 120, 320, 240)
    assert cluttered.orbit == calibrated.orbit
    for name, base in (("calibrated", calibrated), ("cluttered", cluttered)):
        noisy = preset_config(f"{name}-noisy")
        assert noisy.render.depth_noise == DepthNoiseConfig()
        assert dataclasses.replace(noisy, preset=name, render=base.render) == base
    # noise off: the recorded render config has no depth_noise key (the bytes of earlier datasets); on: all of it
    assert "depth_noise" not in recorded_config(calibrated)["render"]
    assert recorded_config(preset_config("calibrated-noisy"))["render"]["depth_noise"]["baseline_m"] == 0.075


@pytest.fixture(scope="module")
def clean_and_noisy(tmp_path_factory):
    """One tiny scene of 4 frames (Workbench images), generated without and with --depth-noise kinect."""
    root = tmp_path_factory.mktemp("noise")
    args = ["--preset", "tiny", "--scenes", "1", "--frames", "4", "--renderer", "workbench", "--quiet"]
    assert main([*args, "--out", str(root / "clean")]) == 0
    assert main([*args, "--out", str(root / "noisy"), "--depth-noise", "kinect"]) == 0
    assert main([*args, "--out", str(root / "noisy"), "--depth-noise", "kinect"]) == 0  # resumes: same config
    return root / "clean", root / "noisy"


def test_noise_leaves_the_ground_truth_exact(clean_and_noisy):
    import cv2

    clean, noisy = clean_and_noisy
    video = "videos/000000"
    for name in ("scene_gt.json", "scene_camera.json", "scene_info.json"):
        assert (clean / video / name).read_bytes() == (noisy / video / name).read_bytes()
    frames = sorted(p.name for p in (clean / video / "mask_inst").iterdir())
    assert len(frames) == 4
    for f in frames:
        assert (clean / video / "mask_inst" / f).read_bytes() == (noisy / video / "mask_inst" / f).read_bytes()
        d0 = cv2.imread(str(clean / video / "depth" / f), cv2.IMREAD_UNCHANGED).astype(np.float64)
        d1 = cv2.imread(str(noisy / video / "depth" / f), cv2.IMREAD_UNCHANGED).astype(np.float64)
        both = (d0 > 0) & (d1 > 0)
        assert (d1[d0 == 0] == 0).all() and 0 < (d1 == 0).mean() < 0.5 and both.mean() > 0.5
        assert np.median(np.abs(d1 - d0)[both]) * 0.1 < 5.0  # mm: noise, not another scene
        assert (d1[both] != d0[both]).mean() > 0.3
    info_clean = json.loads((clean / "dataset_info.json").read_text())
    info_noisy = json.loads((noisy / "dataset_info.json").read_text())
    assert "depth_noise" not in info_clean["config"]["render"]
    assert info_noisy["config"]["render"]["depth_noise"] == dataclasses.asdict(DepthNoiseConfig())
