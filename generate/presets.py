"""Generation config (a dataclass, loaded through :mod:`selfseg.config`) and the named presets.

* ``tiny``: CI data, the whole generation takes well under 3 minutes on 2 cores. 4 objects per
  scene drawn from 6 (four of them multi-part: mug, dumbbell, bottle, lamp), so every object
  reappears in about 3 of the 5 scenes and graph matching has something to merge; the camera
  orbits as close as in ``benchmark``.
* ``small``: a quick experiment at 320×240.
* ``benchmark``: the paper's setting at a size 2 cores can run: 12 scenes × 120 frames at
  320×240, 6 objects per scene drawn from 10 (six of them multi-part non-convex), so every object
  reappears in about 7 scenes; the orbit is configured closer (0.38–0.48 m), then scaled to fit the pile:
  measured camera distance 0.69–1.19 m from the orbit centre, objects 38–72 px (per-scene medians).
* ``calibrated``: the paper's over-segmentation statistics: 12 scenes × 120 frames at 320×240,
  8 objects per scene from the 13 chunky multi-part toys of the ``paper`` library, dropped apart
  (``spread``, .25 m) so that objects rarely touch (0.54 touching pairs per scene on dev seeds 7 and 11);
  camera 0.90–1.16 m from the orbit centre, objects 35–44 px (seed 7).
* ``cluttered``: ``calibrated``'s library, orbit and size at the paper's density: 12 of the 13 ``paper`` toys per
  scene (every object in about 11 of the 12 scenes), dropped in one pile (``pile``, the default .15 m drop disc)
  so that objects touch (9.8 touching pairs per scene, all 12 objects kept; dev seed 7, scenes 0–4).
* ``calibrated-noisy``, ``cluttered-noisy``: the same with structured-light depth noise
  (``render.depth_noise``: the Kinect v1 defaults of :class:`~selfseg.generate.depth_noise.DepthNoiseConfig`).
* ``demo``: what ``make demo`` runs: ``calibrated``'s layout at demo size, 6 scenes × 36 frames at 160×120, 4 of 6
  ``paper`` toys per scene (each in about 4 scenes), dropped apart, so that matching has objects to merge.
* ``paper-synthetic``: as in the paper: 36 videos × 800 frames, 12 objects per scene drawn from
  a fixed 17-object subset, 640×480. ``frame_step`` n renders only every n-th frame.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from selfseg.config import from_dict, to_dict
from selfseg.generate.physics import PhysicsConfig
from selfseg.generate.render import RenderConfig

GENERATOR_VERSION = "selfseg.generate 1"
LIBRARIES = ("builtin", "paper")  # the object libraries built in code (generate/objects.py)


@dataclass
class OrbitConfig:
    """Camera orbit around the scene centre (metres, degrees). Per scene, the mean radius and
    height are drawn from the ranges; both then fluctuate sinusoidally over the video."""

    hfov_deg: float = 58.0  # horizontal field of view (RealSense-like)
    radius_m: tuple[float, float] = (0.5, 0.65)  # mean horizontal distance to the scene centre
    radius_amplitude_m: float = 0.05
    height_m: tuple[float, float] = (0.35, 0.5)  # mean camera height above the table
    height_amplitude_m: float = 0.06
    arc_deg: float = 360.0  # azimuth swept by the full video (capped by max_step_deg per frame)
    max_step_deg: float = 1.8  # largest azimuth step between full-rate frames (view change stays ≤ 2°)

    def __post_init__(self) -> None:
        if not 10.0 <= self.hfov_deg <= 120.0:
            raise ValueError(f"orbit.hfov_deg must be in [10, 120], got {self.hfov_deg}")
        if not (0 < self.radius_m[0] <= self.radius_m[1]) or not (0 < self.height_m[0] <= self.height_m[1]):
            raise ValueError(f"orbit.radius_m and orbit.height_m must be increasing positive ranges, "
                             f"got {self.radius_m} and {self.height_m}")
        if self.max_step_deg <= 0 or self.arc_deg <= 0:
            raise ValueError("orbit.arc_deg and orbit.max_step_deg must be positive")


@dataclass
class GenerateConfig:
    """Everything that determines a generated dataset (recorded in dataset_info.json)."""

    preset: str = "tiny"
    scenes: int = 5
    frames: int = 36  # frames of the full-rate video
    frame_step: int = 1  # render every n-th frame of the full-rate video (frame ids keep the full-rate index)
    width: int = 160
    height: int = 120
    objects_per_scene: int = 4
    library: str = "builtin"  # "builtin" (25 objects) or "paper" (chunky multi-part toys)
    objects_dir: str | None = None  # folder of user meshes; None = the `library`
    object_pool: list[str] | None = None  # names of library objects to use; None = all of them
    min_kept_fraction: float = 0.75  # re-drop a scene if fewer than this share of its objects stay on the table
    seed: int = 0
    render: RenderConfig = field(default_factory=RenderConfig)
    orbit: OrbitConfig = field(default_factory=OrbitConfig)
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)

    def __post_init__(self) -> None:
        for name in ("scenes", "frames", "frame_step", "width", "height", "objects_per_scene"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.width > 4096 or self.height > 4096:
            raise ValueError(f"resolution {self.width}x{self.height} is larger than 4096x4096")
        if self.library not in LIBRARIES:
            raise ValueError(f"library must be one of {', '.join(LIBRARIES)}, got {self.library!r}")
        if not 0.0 < self.min_kept_fraction <= 1.0:
            raise ValueError(f"min_kept_fraction must be in (0, 1], got {self.min_kept_fraction}")

    @property
    def frame_ids(self) -> list[int]:
        """Ids of the rendered frames (indices into the full-rate video)."""
        return list(range(0, self.frames, self.frame_step))


BENCHMARK_POOL = ["lamp", "dumbbell", "mug", "bowl", "bottle", "duck", "hammer", "banana", "box_medium", "can_soda"]
TINY_POOL = ["mug", "dumbbell", "bottle", "lamp", "bowl", "box_medium"]
CLOSE_ORBIT = {"radius_m": (0.38, 0.48), "height_m": (0.3, 0.4), "radius_amplitude_m": 0.04, "height_amplitude_m": 0.05}


def _paper_pool() -> list[str]:
    from selfseg.generate.objects import PAPER_SUBSET

    return list(PAPER_SUBSET)


PRESETS: dict[str, dict] = {
    # 5 scenes × 36 frames at 160×120, 4 of 6 objects per scene (each object appears ~3.3 times)
    "tiny": {"scenes": 5, "frames": 36, "width": 160, "height": 120, "objects_per_scene": 4,
             "object_pool": TINY_POOL, "orbit": CLOSE_ORBIT},
    "small": {"scenes": 12, "frames": 120, "width": 320, "height": 240, "objects_per_scene": 8},
    "benchmark": {"scenes": 12, "frames": 120, "width": 320, "height": 240, "objects_per_scene": 6,
                  "object_pool": BENCHMARK_POOL, "orbit": CLOSE_ORBIT},
    # the paper's Table II statistics, on development seeds: the `paper` toys, contact rare
    "calibrated": {"scenes": 12, "frames": 120, "width": 320, "height": 240, "objects_per_scene": 8,
                   "library": "paper", "orbit": CLOSE_ORBIT,
                   "physics": {"layout": "spread", "drop_radius_m": 0.25, "spread_gap_m": 0.01}},
    # the demo: calibrated's layout at 160×120, few scenes (docs/experiments/2026-11-26-demo-preset-candidate.md)
    "demo": {"scenes": 6, "frames": 36, "width": 160, "height": 120, "objects_per_scene": 4, "library": "paper",
             "object_pool": ["toy_car", "toy_rocket", "snowman", "toy_robot", "mushroom", "toy_house"],
             "orbit": CLOSE_ORBIT, "physics": {"layout": "spread", "drop_radius_m": 0.25, "spread_gap_m": 0.01}},
    # the paper's density: 12 toys per scene in one pile
    "cluttered": {"scenes": 12, "frames": 120, "width": 320, "height": 240, "objects_per_scene": 12,
                  "library": "paper", "orbit": CLOSE_ORBIT},
    "paper-synthetic": {"scenes": 36, "frames": 800, "width": 640, "height": 480, "objects_per_scene": 12,
                        "object_pool": None},  # filled with PAPER_SUBSET by preset_config
}
# the same with the depth noise on ({}: DepthNoiseConfig's defaults)
PRESETS.update({f"{name}-noisy": {**PRESETS[name], "render": {"depth_noise": {}}}
                for name in ("calibrated", "cluttered")})


def preset_config(name: str, **overrides) -> GenerateConfig:
    """The named preset with field overrides (None values are ignored), validated."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    data = to_dict(GenerateConfig())
    preset = dict(PRESETS[name])
    for key in ("render", "orbit", "physics"):
        if key in preset:
            preset[key] = {**data[key], **preset[key]}
    data.update(preset, preset=name)
    if name == "paper-synthetic":
        data["object_pool"] = _paper_pool()
    if overrides.get("objects_dir") is not None:
        data["object_pool"] = None  # user objects: use all of them
    for key, value in overrides.items():
        if value is None:
            continue
        if key in ("render", "orbit", "physics"):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    return from_dict(GenerateConfig, data)

