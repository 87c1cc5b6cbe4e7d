"""Procedural texture images for the object library and the table (deterministic per seed).

Every function returns an H×W×3 uint8 RGB image. Images follow the usual UV convention of
:mod:`selfseg.generate.objects`: texture coordinate v = 0 is the *last* row of the array
(bottom of the image), v = 1 the first row; u = 0 is the first column.
"""
from __future__ import annotations

import colorsys
import hashlib

import cv2
import numpy as np

PATTERNS = ("solid", "stripes", "diag_stripes", "checks", "dots", "noise", "marble", "label", "plaid",
            "gradient", "speckle", "wood")

# Named base colours (RGB 0..255) used by the object specs.
COLORS: dict[str, tuple[int, int, int]] = {
    "red": (200, 30, 35), "dark_red": (120, 20, 25), "orange": (235, 120, 20), "yellow": (240, 205, 40),
    "lime": (150, 210, 50), "green": (40, 140, 60), "dark_green": (20, 80, 40), "teal": (20, 150, 150),
    "cyan": (60, 200, 230), "blue": (35, 75, 190), "navy": (20, 30, 90), "purple": (120, 50, 160),
    "magenta": (210, 50, 150), "pink": (245, 150, 180), "brown": (120, 75, 35), "tan": (210, 170, 120),
    "beige": (235, 220, 190), "white": (245, 245, 240), "grey": (140, 140, 145), "silver": (190, 195, 200),
    "black": (25, 25, 28), "terracotta": (190, 95, 60), "gold": (210, 165, 50),
}


def seed_from_name(name: str) -> int:
    """A stable 32-bit seed derived from a string (independent of Python's hash randomisation)."""
    return int.from_bytes(hashlib.sha256(name.encode("utf-8")).digest()[:4], "little")


def _rgb(c: str | tuple[int, int, int]) -> np.ndarray:
    return np.asarray(COLORS[c] if isinstance(c, str) else c, dtype=np.float64)


def _smooth_noise(rng: np.random.Generator, h: int, w: int, cells: int) -> np.ndarray:
    """Value noise in [0, 1]: a coarse random grid upsampled bicubically."""
    coarse = rng.random((cells + 3, cells + 3)).astype(np.float32)
    big = cv2.resize(coarse, (w + 3 * w // cells, h + 3 * h // cells), interpolation=cv2.INTER_CUBIC)
    n = big[h // cells: h // cells + h, w // cells: w // cells + w]
    return np.clip((n - n.min()) / max(float(n.max() - n.min()), 1e-6), 0.0, 1.0)


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return a[None, None, :] * (1.0 - t[..., None]) + b[None, None, :] * t[..., None]


def make_texture(pattern: str, colors: tuple, seed: int, size: tuple[int, int] = (256, 256),
                 text: str | None = None) -> np.ndarray:
    """One procedural texture.

    ``pattern`` is one of :data:`PATTERNS`; ``colors`` two colour names or RGB triples (primary,
    secondary); ``size`` is (height, width) in pixels; ``text`` is printed by the ``label`` pattern.
    The same arguments always give the same image.
    """
    if pattern not in PATTERNS:
        raise ValueError(f"unknown texture pattern {pattern!r}; choose one of {PATTERNS}")
    h, w = size
    rng = np.random.default_rng(seed)
    c0, c1 = _rgb(colors[0]), _rgb(colors[1] if len(colors) > 1 else colors[0])
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    period = float(rng.integers(5, 11))  # repeats across the image
    if pattern == "solid":
        t = np.zeros((h, w))
    elif pattern == "stripes":
        t = (np.floor(yy / h * period * 2) % 2).astype(np.float64)
    elif pattern == "diag_stripes":
        t = (np.floor((xx / w + yy / h) * period) % 2).astype(np.float64)
    elif pattern == "checks":
        t = ((np.floor(xx / w * period) + np.floor(yy / h * period)) % 2).astype(np.float64)
    elif pattern == "dots":
        cell = w / period
        fx, fy = (xx % cell) / cell - 0.5, (yy % cell) / cell - 0.5
        t = ((fx ** 2 + fy ** 2) < 0.09).astype(np.float64)
    elif pattern == "noise":
        t = _smooth_noise(rng, h, w, 8)
    elif pattern == "marble":
        n = _smooth_noise(rng, h, w, 6)
        t = 0.5 + 0.5 * np.sin((xx / w * period + 4.0 * n) * np.pi)
    elif pattern == "plaid":
        a = (np.floor(xx / w * period * 2) % 2) * 0.5
        b = (np.floor(yy / h * period * 2) % 2) * 0.5
        t = a + b
    elif pattern == "gradient":
        t = yy / max(h - 1, 1)
    elif pattern == "speckle":
        t = (rng.random((h, w)) < 0.04).astype(np.float64)
        t = cv2.GaussianBlur(t.astype(np.float32), (0, 0), 1.2).astype(np.float64)
        t = np.clip(t * 3.0, 0.0, 1.0)
    elif pattern == "wood":
        n = _smooth_noise(rng, h, w, 4)
        t = 0.5 + 0.5 * np.sin((yy / h * period * 3 + 6.0 * n) * np.pi)
    else:  # "label": primary colour with a secondary band, printed text and a bar code
        t = ((yy > 0.3 * h) & (yy < 0.7 * h)).astype(np.float64)
    img = _mix(c0, c1, t)
    # Subtle per-pixel grain so that no surface is perfectly flat in colour.
    img += rng.normal(0.0, 6.0, size=(h, w, 1))
    img = np.clip(img, 0, 255).astype(np.uint8)
    if pattern == "label":
        _print_label(img, text or "", c0, rng)
    return img


def _print_label(img: np.ndarray, text: str, ink: np.ndarray, rng: np.random.Generator) -> None:
    """Print ``text`` twice across the label band and a bar code under it (in place)."""
    h, w = img.shape[:2]
    ink_c = tuple(int(v) for v in ink)
    if text:
        scale = 0.9 * w / max(cv2.getTextSize(text, cv2.FONT_HERSHEY_DUPLEX, 1.0, 2)[0][0] * 2.2, 1)
        thick = max(1, int(round(2 * scale)))
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_DUPLEX, scale, thick)
        for x0 in (int(0.04 * w), int(0.54 * w)):
            cv2.putText(img, text, (x0, int(0.5 * h + th / 2)), cv2.FONT_HERSHEY_DUPLEX, scale, ink_c, thick,
                        cv2.LINE_AA)
    bars = rng.integers(1, 4, size=40)
    x = int(0.1 * w)
    for i, b in enumerate(bars):
        if i % 2 == 0 and x + b < 0.45 * w:
            img[int(0.58 * h): int(0.67 * h), x: x + b] = ink_c
        x += int(b)


def atlas(textures: list[np.ndarray]) -> np.ndarray:
    """Stack part textures vertically into one atlas (all resized to the first one's width)."""
    w = textures[0].shape[1]
    rows = [t if t.shape[1] == w else cv2.resize(t, (w, max(1, round(t.shape[0] * w / t.shape[1]))),
                                                 interpolation=cv2.INTER_AREA) for t in textures]
    return np.ascontiguousarray(np.concatenate(rows, axis=0))


def table_texture(seed: int, size: tuple[int, int] = (512, 512)) -> np.ndarray:
    """A random table-top texture (wood, marble, checks, noise or plaid in muted colours) for one scene."""
    rng = np.random.default_rng(seed)
    pattern = ("wood", "marble", "checks", "noise", "plaid")[int(rng.integers(5))]
    hue = rng.random()
    c0 = np.array(colorsys.hsv_to_rgb(hue, 0.15 + 0.35 * rng.random(), 0.35 + 0.45 * rng.random())) * 255
    c1 = np.clip(c0 * (0.6 + 0.3 * rng.random()), 0, 255)
    return make_texture(pattern, (tuple(c0.round().astype(int)), tuple(c1.round().astype(int))),
                        int(rng.integers(2**31)), size)
