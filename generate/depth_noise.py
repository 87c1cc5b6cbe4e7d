"""Depth-sensor noise for rendered depth: a structured-light (Kinect v1) model, applied to depth only.

The renderer's planar depth (metres, 0 = no surface) is exact. :func:`add_depth_noise` turns it into what a
structured-light camera would measure; masks, poses and cameras stay exact. One function per effect:

- :func:`lateral_jitter`: each pixel reads the depth of a Gaussian-shifted pixel (nearest neighbour), as
  simkinect's ``add_gaussian_shifts`` does (Handa, Whelan, McDonald & Davison 2014, ICRA; σ = 1/2 px at
  640×480, :attr:`DepthNoiseConfig.lateral_sigma_px`). Metric lateral error grows with distance (z·σ/f).
- :func:`disparity_noise`: the sensor triangulates disparity d = f·b/z (sensor px) between its IR camera
  (focal f) and its projector (baseline b), adds Gaussian noise and stores it in 1/8-px steps. Khoshelham &
  Oude Elberink 2012 (Sensors 12(2):1437), Kinect v1: b = 7.5 cm, f ≈ 580 px, steps of 1/8 px, random error
  σ_d = 1/2 step, so σ_z ≈ z²/(f·b)·√(σ_d² + step²/12) grows with the square of the distance (1.7 mm at
  1 m, 6.6 mm at 2 m). The 1/8-px rounding is also Barron & Malik 2013 (CVPR)'s and simkinect's.
- :func:`projector_shadow`: pixels the projector cannot light (it sits b along the camera's +x) get no
  depth: on a row, pixel u is shadowed when a pixel u' > u has projector column u' − d' < u − d (a 2.5-D
  test: surfaces are assumed solid behind what the camera sees).
- :func:`edge_dropout`: the sensor's correlation window (simkinect: 9×9 sensor px) fails where it
  straddles a depth jump; pixels within :attr:`~DepthNoiseConfig.edge_radius_px` of a disparity jump (a
  second difference along a row or column above ``edge_jump_px``; planes have none) or of a pixel
  without depth are dropped with probability ``edge_dropout`` (which pixels fail depends on the speckle
  pattern; the probability is this module's choice).
- :func:`grazing_dropout`: at grazing incidence the pattern's dots smear out. Nguyen, Izadi & Lovell 2012
  (3DIMPVT) measure an axial noise term θ²/(π/2 − θ)² that diverges as θ → 90° (θ between the viewing
  ray and the surface normal, normals from the clean depth map); the dropout probability rises linearly
  in cos θ from 0 at ``grazing_start_deg`` to 1 at ``grazing_full_deg`` (this module's choice).
- :func:`axial_noise` (optional, off by default): Gaussian depth noise growing with distance, Nguyen et
  al. 2012's distance term σ_z = 0.0012 + 0.0019 (z − 0.4)² m (the same kind of model as BlenderProc's
  Kinect Azure noise, 0.5 mm + 1 mm/m). It is their measured *total* noise: use it instead of, not with,
  the disparity noise.

Sensor pixels are converted to image pixels by f_image/f_sensor, so the metric noise does not depend on
the render resolution. Missing pixels are depth 0 (the format's "no measurement").

Determinism: the result is a pure function of (clean depth, K, config, :func:`frame_rng`'s seed), identical on
every x86-64 CPU. Every array operation is an IEEE-754 basic operation (+ − × ÷ √, correctly rounded at any
SIMD width numpy dispatches), a comparison, rounding to integers, a running minimum or a boolean dilation;
there are no reductions whose summation order could change, no BLAS and no transcendental functions on arrays
(the two grazing cosines are Python scalars). numpy's PCG64 bits are integer arithmetic; only
``standard_normal``'s rare ziggurat tail calls libm, which ``generate_scenes`` pins, and even unpinned a
last-bit difference changes a written value only if it lies within one ulp of a boundary of the 1/8-px or
0.1 mm grids (about 1e-12 per pixel).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

NOISE_STREAM = 0x6E6F6973  # appended to the seed: the noise's random stream is apart from the scene's other draws


@dataclass
class DepthNoiseConfig:
    """Structured-light noise parameters; defaults are the Kinect v1 values cited in the module docstring.
    Pixel quantities are in sensor pixels (``sensor_focal_px``), converted to image pixels per frame."""

    baseline_m: float = 0.075  # IR camera to projector, along the camera's +x
    sensor_focal_px: float = 580.0  # focal length of the sensor's IR camera
    disparity_sigma_px: float = 0.0625  # Gaussian disparity noise (1/2 of a 1/8-px step)
    disparity_step_px: float = 0.125  # disparity quantisation step; 0 = none
    lateral_sigma_px: float = 0.5  # std of the pixel shift in x and in y
    projector_shadow: bool = True  # drop pixels the projector cannot light
    edge_jump_px: float = 0.5  # a disparity second difference above this is a depth edge
    edge_radius_px: float = 4.0  # pixels this close to an edge (Chebyshev distance) may drop out ...
    edge_dropout: float = 0.5  # ... with this probability
    grazing_start_deg: float = 70.0  # incidence angle where dropout starts ...
    grazing_full_deg: float = 85.0  # ... and where every pixel drops out
    axial: bool = False  # add Nguyen et al.'s axial noise, σ_z(z) = axial_sigma_m + axial_growth_per_m2 ·
    # (z − axial_offset_m)², in m
    axial_sigma_m: float = 0.0012
    axial_growth_per_m2: float = 0.0019
    axial_offset_m: float = 0.4

    def __post_init__(self) -> None:
        for name in ("baseline_m", "sensor_focal_px"):
            if getattr(self, name) <= 0:
                raise ValueError(f"depth_noise.{name} must be positive, got {getattr(self, name)}")
        for name in ("disparity_sigma_px", "disparity_step_px", "lateral_sigma_px", "edge_jump_px", "edge_radius_px",
                     "axial_sigma_m", "axial_growth_per_m2"):
            if getattr(self, name) < 0:
                raise ValueError(f"depth_noise.{name} must be >= 0, got {getattr(self, name)}")
        if not 0.0 <= self.edge_dropout <= 1.0:
            raise ValueError(f"depth_noise.edge_dropout must be a probability, got {self.edge_dropout}")
        if not 0.0 <= self.grazing_start_deg < self.grazing_full_deg <= 90.0:
            raise ValueError("depth_noise needs 0 <= grazing_start_deg < grazing_full_deg <= 90, got "
                             f"{self.grazing_start_deg} and {self.grazing_full_deg}")


def frame_rng(scene_seed: int, frame_id: int) -> np.random.Generator:
    """The noise's random generator for frame ``frame_id`` of the scene with seed ``scene_seed``."""
    return np.random.default_rng([scene_seed, frame_id, NOISE_STREAM])


def to_disparity(depth_m: np.ndarray, focal_px: float, baseline_m: float) -> np.ndarray:
    """Disparity f·b/z (px, float64); 0 where the depth is 0."""
    valid = depth_m > 0
    return np.where(valid, focal_px * baseline_m / np.where(valid, depth_m, 1.0), 0.0)


def lateral_jitter(depth_m: np.ndarray, sigma_px: float, rng: np.random.Generator) -> np.ndarray:
    """Each pixel takes the depth of the pixel nearest to a shift by N(0, sigma_px²) in x and y (image px),
    clamped to the image."""
    h, w = depth_m.shape
    shift = np.rint(rng.standard_normal((2, h, w)) * sigma_px).astype(np.int64)
    rows = np.clip(np.arange(h)[:, None] + shift[1], 0, h - 1)
    cols = np.clip(np.arange(w)[None, :] + shift[0], 0, w - 1)
    return depth_m[rows, cols]


def disparity_noise(disparity_px: np.ndarray, sigma_px: float, step_px: float,
                    rng: np.random.Generator) -> np.ndarray:
    """Disparity plus N(0, sigma_px²), rounded to multiples of ``step_px`` (none when 0)."""
    noisy = disparity_px + sigma_px * rng.standard_normal(disparity_px.shape)
    return np.rint(noisy / step_px) * step_px if step_px > 0 else noisy


def projector_shadow(depth_m: np.ndarray, fx_px: float, baseline_m: float, tol_px: float = 1e-3) -> np.ndarray:
    """Pixels (with depth) that a projector ``baseline_m`` along the camera's +x cannot light: pixel u of a row,
    at projector column u − d (d = fx·b/z, image px), is shadowed when a pixel u' > u of the row has
    u' − d' < u − d − ``tol_px``."""
    valid = depth_m > 0
    column = np.arange(depth_m.shape[1], dtype=np.float64)[None, :]
    proj = np.where(valid, column - to_disparity(depth_m, fx_px, baseline_m), np.inf)
    right_min = np.full_like(proj, np.inf)
    right_min[:, :-1] = np.minimum.accumulate(proj[:, :0:-1], axis=1)[:, ::-1]  # min over u' > u
    return valid & (right_min < proj - tol_px)


def edge_mask(disparity_px: np.ndarray, jump_px: float, radius_px: int) -> np.ndarray:
    """Pixels with depth within ``radius_px`` (Chebyshev, image px) of a depth edge: a pixel whose disparity's
    second difference along its row or column exceeds ``jump_px``, or a pixel next to one without depth."""
    valid = disparity_px > 0
    edge = np.zeros(disparity_px.shape, bool)
    for axis in (0, 1):
        d = np.moveaxis(disparity_px, axis, 0)
        v = np.moveaxis(valid, axis, 0)
        e = np.moveaxis(edge, axis, 0)  # a view: writes land in `edge`
        e[1:-1] |= np.abs(d[2:] - 2.0 * d[1:-1] + d[:-2]) > jump_px
        e[1:] |= ~v[:-1]
        e[:-1] |= ~v[1:]
    if radius_px > 0:
        edge = ndimage.binary_dilation(edge, structure=np.ones((2 * radius_px + 1,) * 2, bool))
    return edge & valid


def edge_dropout(disparity_px: np.ndarray, jump_px: float, radius_px: int, probability: float,
                 rng: np.random.Generator) -> np.ndarray:
    """Pixels of :func:`edge_mask` that drop out, each with ``probability``."""
    return edge_mask(disparity_px, jump_px, radius_px) & (rng.random(disparity_px.shape) < probability)


def _tangent(points: np.ndarray, valid: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the difference to its neighbour along ``axis`` (1 = next column, 0 = next row) on the side whose
    depth differs less (3×H×W, camera frame, m), and whether one exists."""
    sl = lambda a, b: tuple(slice(a, b) if i == axis else slice(None) for i in range(2))  # noqa: E731
    diff = points[(slice(None), *sl(1, None))] - points[(slice(None), *sl(None, -1))]  # p[i+1] − p[i]
    pair = valid[sl(1, None)] & valid[sl(None, -1)]
    fwd, fwd_ok = np.zeros_like(points), np.zeros(valid.shape, bool)
    fwd[(slice(None), *sl(None, -1))], fwd_ok[sl(None, -1)] = diff, pair
    bwd, bwd_ok = np.zeros_like(points), np.zeros(valid.shape, bool)
    bwd[(slice(None), *sl(1, None))], bwd_ok[sl(1, None)] = diff, pair
    use_fwd = fwd_ok & (~bwd_ok | (np.abs(fwd[2]) <= np.abs(bwd[2])))
    return np.where(use_fwd, fwd, bwd), fwd_ok | bwd_ok


def incidence_cos(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """cos θ of the angle between each pixel's viewing ray and the surface normal, from the depth map's
    back-projected neighbours (float64, H×W); 1 where the pixel or both neighbours on an axis have no depth."""
    h, w = depth_m.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    valid = depth_m > 0
    z = depth_m.astype(np.float64)
    points = np.stack([(np.arange(w)[None, :] - cx) / fx * z, (np.arange(h)[:, None] - cy) / fy * z, z])
    tu, ok_u = _tangent(points, valid, axis=1)
    tv, ok_v = _tangent(points, valid, axis=0)
    n = np.stack([tu[1] * tv[2] - tu[2] * tv[1], tu[2] * tv[0] - tu[0] * tv[2], tu[0] * tv[1] - tu[1] * tv[0]])
    norm = np.sqrt((n[0] * n[0] + n[1] * n[1] + n[2] * n[2]) * (points[0] * points[0] + points[1] * points[1]
                                                                  + points[2] * points[2]))
    known = valid & ok_u & ok_v & (norm > 0)
    dot = np.abs(n[0] * points[0] + n[1] * points[1] + n[2] * points[2])
    return np.where(known, dot / np.where(known, norm, 1.0), 1.0)


def grazing_probability(cos_theta: np.ndarray, start_deg: float, full_deg: float) -> np.ndarray:
    """Dropout probability: 0 at incidence ``start_deg`` and below, rising linearly in cos θ to 1 at ``full_deg``."""
    c0, c1 = math.cos(math.radians(start_deg)), math.cos(math.radians(full_deg))
    return np.clip((c0 - cos_theta) / (c0 - c1), 0.0, 1.0)


def grazing_dropout(depth_m: np.ndarray, K: np.ndarray, start_deg: float, full_deg: float,
                    rng: np.random.Generator) -> np.ndarray:
    """Pixels that drop out at grazing incidence, each with :func:`grazing_probability`."""
    p = grazing_probability(incidence_cos(depth_m, K), start_deg, full_deg)
    return rng.random(depth_m.shape) < p


def axial_sigma_m(depth_m: np.ndarray, cfg: DepthNoiseConfig) -> np.ndarray:
    """Nguyen et al. 2012's axial standard deviation (m) at depth ``depth_m`` (m)."""
    return cfg.axial_sigma_m + cfg.axial_growth_per_m2 * (depth_m - cfg.axial_offset_m) ** 2


def axial_noise(depth_m: np.ndarray, cfg: DepthNoiseConfig, rng: np.random.Generator) -> np.ndarray:
    """Depth plus N(0, axial_sigma_m(z)²)."""
    return depth_m + axial_sigma_m(depth_m, cfg) * rng.standard_normal(depth_m.shape)


def add_depth_noise(depth_m: np.ndarray, K: np.ndarray, cfg: DepthNoiseConfig,
                    rng: np.random.Generator) -> np.ndarray:
    """The depth a structured-light sensor measures (float32 m, 0 = no measurement) for a clean planar depth map
    ``depth_m`` (m, 0 = no surface) seen through intrinsics ``K`` (OpenCV, image px)."""
    depth = np.asarray(depth_m, dtype=np.float64)
    fx = float(K[0, 0])
    to_image = fx / cfg.sensor_focal_px  # image px per sensor px
    disparity = to_disparity(depth, cfg.sensor_focal_px, cfg.baseline_m)
    # the draws come in a fixed order and the dropouts draw whatever their probability, so switching one effect
    # leaves the others' noise unchanged (the optional axial noise draws last)
    dropped = edge_dropout(disparity, cfg.edge_jump_px, int(math.floor(cfg.edge_radius_px * to_image + 0.5)),
                           cfg.edge_dropout, rng)
    dropped |= grazing_dropout(depth, K, cfg.grazing_start_deg, cfg.grazing_full_deg, rng)
    if cfg.projector_shadow:
        dropped |= projector_shadow(depth, fx, cfg.baseline_m)
    jittered = lateral_jitter(depth, cfg.lateral_sigma_px * to_image, rng)
    measured = disparity_noise(to_disparity(jittered, cfg.sensor_focal_px, cfg.baseline_m), cfg.disparity_sigma_px,
                               cfg.disparity_step_px, rng)
    keep = ~dropped & (jittered > 0) & (measured > 0)
    out = np.where(keep, cfg.sensor_focal_px * cfg.baseline_m / np.where(keep, measured, 1.0), 0.0)
    if cfg.axial:
        out = axial_noise(out, cfg, rng)
        out = np.where(keep & (out > 0), out, 0.0)
    return out.astype(np.float32)
