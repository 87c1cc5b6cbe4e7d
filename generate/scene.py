"""One generated scene, end to end: pick objects, drop them with physics, orbit and render.

Frames: world z up, table top at z = 0; camera poses OpenCV ``T_world_cam``; metres.
A scene is written into a temporary folder and renamed to ``videos/NNNNNN`` only when complete.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from selfseg.fileio import atomic_dir
from selfseg.generate.depth_noise import add_depth_noise, frame_rng
from selfseg.generate.determinism import snap, snap_pose
from selfseg.generate.objects import ObjectModel
from selfseg.generate.physics import drop_objects
from selfseg.generate.presets import GenerateConfig, OrbitConfig
from selfseg.generate.render import BlenderScene, intrinsics, sample_appearance
from selfseg.poses import invert_T, transform_points
from selfseg.raycast import look_at
from selfseg.writers import VideoWriter

STAGES = ("physics", "blender_setup", "render_image", "render_gt", "write")


def scene_seed(dataset_seed: int, index: int) -> int:
    """The seed of scene ``index`` of a dataset (a 32-bit hash of both)."""
    return int(np.random.SeedSequence([dataset_seed, index]).generate_state(1)[0])


def choose_objects(rng: np.random.Generator, library_size: int, k: int) -> list[int]:
    """Library indices of a scene's ``k`` distinct objects (sorted)."""
    return sorted(int(i) for i in rng.choice(library_size, size=k, replace=False))


def orbit_step_deg(cfg: OrbitConfig, frames: int) -> float:
    """Azimuth step between consecutive full-rate frames: ``min(max_step_deg, arc_deg / (frames − 1))``."""
    return cfg.max_step_deg if frames < 2 else min(cfg.max_step_deg, cfg.arc_deg / (frames - 1))


def camera_orbit(cfg: OrbitConfig, frames: int, center: np.ndarray, rng: np.random.Generator,
                 extent_m: float = 0.0, vfov_deg: float | None = None) -> tuple[list[np.ndarray], dict]:
    """Full-rate camera poses (OpenCV T_world_cam) orbiting ``center`` and the orbit's parameters.

    The azimuth advances by :func:`orbit_step_deg` per frame; radius and height fluctuate
    sinusoidally, twice per full turn, so neighbouring views differ by about the step. If the
    objects reach ``extent_m`` from the centre, the orbit is scaled up until a sphere of that
    radius fits the vertical field of view ``vfov_deg`` at the orbit's smallest distance, so every
    object stays in view.
    """
    step = orbit_step_deg(cfg, frames)
    r0, h0 = rng.uniform(*cfg.radius_m), rng.uniform(*cfg.height_m)
    scale = 1.0
    if extent_m > 0 and vfov_deg is not None:
        nearest = math.hypot(r0 - cfg.radius_amplitude_m, h0 - cfg.height_amplitude_m - center[2])
        scale = max(1.0, extent_m / math.sin(math.radians(vfov_deg) / 2) / nearest)
    params = {"center": np.asarray(center, float).round(5).tolist(), "azimuth0_deg": float(rng.uniform(0, 360)),
              "step_deg": float(step), "scale": scale, "radius_m": r0 * scale,
              "radius_amplitude_m": cfg.radius_amplitude_m * scale, "height_m": h0 * scale,
              "height_amplitude_m": cfg.height_amplitude_m * scale, "phase_radius": float(rng.uniform(0, 2 * np.pi)),
              "phase_height": float(rng.uniform(0, 2 * np.pi)), "waves_per_turn": 2.0, "hfov_deg": cfg.hfov_deg}
    poses = []
    for i in range(frames):
        a = math.radians(params["azimuth0_deg"] + step * i)
        swept = math.radians(step * i) * params["waves_per_turn"]
        r = params["radius_m"] + params["radius_amplitude_m"] * math.sin(swept + params["phase_radius"])
        h = params["height_m"] + params["height_amplitude_m"] * math.sin(swept + params["phase_height"])
        eye = np.array([center[0] + r * math.cos(a), center[1] + r * math.sin(a), h])
        poses.append(snap_pose(look_at(eye, center)))
    return poses, params


def _scene_center(objects: list[ObjectModel], poses: list[np.ndarray]) -> tuple[np.ndarray, float]:
    """Look-at target (centre of the objects' world bounding box in x, y; a third of its height in
    z) and the largest distance of an object vertex from it (m)."""
    pts = np.concatenate([transform_points(o.vertices, T) for o, T in zip(objects, poses)])
    lo, hi = pts.min(0), pts.max(0)
    center = snap([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, max(hi[2], 0.0) / 3])
    return center, float(snap(np.sqrt(((pts - center) ** 2).sum(1)).max()))


def load_library(cfg: GenerateConfig) -> list[ObjectModel]:
    """The dataset's objects, in obj_id order (obj_id = index + 1): the builtin library or the user
    folder, restricted to ``cfg.object_pool``. Raises ValueError for unknown names or too few objects."""
    from selfseg.generate.objects import builtin_library, load_user_objects, paper_library

    if cfg.objects_dir is not None:
        objects = load_user_objects(cfg.objects_dir)
    else:
        objects = paper_library() if cfg.library == "paper" else builtin_library()
    if cfg.object_pool is not None:
        by_name = {o.name: o for o in objects}
        missing = [n for n in cfg.object_pool if n not in by_name]
        if missing:
            raise ValueError(f"object_pool names {missing} are not in the library ({', '.join(by_name)})")
        objects = [by_name[n] for n in cfg.object_pool]
    if cfg.objects_per_scene > len(objects):
        where = cfg.objects_dir or f"the {cfg.library} library" + (" pool" if cfg.object_pool is not None else "")
        raise ValueError(f"{cfg.objects_per_scene} objects per scene requested but {where} has only "
                         f"{len(objects)} objects")
    return objects


def drop_scene(cfg: GenerateConfig, index: int, library: list[ObjectModel], cache_dir: Path | None = None):
    """Scene ``index``'s objects dropped onto the table: (seed, its generator, positioned after the drop for the
    orbit and appearance draws, the chosen library indices, the :class:`DropResult`, and the kept instances as
    (inst_id, library index, T_world_obj) with instance k ≥ 1 the k-th object kept on the table)."""
    seed = scene_seed(cfg.seed, index)
    rng = np.random.default_rng(seed)
    k = cfg.objects_per_scene
    chosen = choose_objects(rng, len(library), k)
    drop = drop_objects([library[i] for i in chosen], seed, cfg.physics, cache_dir=cache_dir,
                        min_kept=max(1, math.ceil(cfg.min_kept_fraction * k)))
    instances = [(n + 1, chosen[j], drop.poses[j]) for n, j in enumerate(sorted(drop.poses))]
    return seed, rng, chosen, drop, instances


def generate_scene(cfg: GenerateConfig, index: int, library: list[ObjectModel], final_dir: str | Path,
                   cache_dir: Path | None = None, progress: bool = True) -> dict:
    """Generate scene ``index`` into ``final_dir`` (atomically) and return its per-stage seconds.

    Object ids are library index + 1; instance k ≥ 1 is the k-th object kept on the table.
    """
    timings = dict.fromkeys(STAGES, 0.0)
    t0 = time.perf_counter()
    seed, rng, chosen, drop, instances = drop_scene(cfg, index, library, cache_dir)
    timings["physics"] = time.perf_counter() - t0
    center, extent = _scene_center([library[li] for _, li, _ in instances], [T for _, _, T in instances])
    K = intrinsics(cfg.width, cfg.height, cfg.orbit.hfov_deg)
    vfov = math.degrees(2 * math.atan(cfg.height / 2 / K[1, 1]))
    cams, orbit = camera_orbit(cfg.orbit, cfg.frames, center, rng, extent, vfov)
    appearance = sample_appearance(rng)

    with atomic_dir(final_dir) as tmp:
        t0 = time.perf_counter()
        with BlenderScene([(i, library[li], T) for i, li, T in instances], appearance, cfg.width, cfg.height, K,
                          cfg.render, seed=seed % (2**31)) as bscene:
            timings["blender_setup"] = time.perf_counter() - t0
            writer = VideoWriter(tmp)
            for fid in tqdm(cfg.frame_ids, desc=f"scene {index:06d} frames", unit="frame", leave=False,
                            disable=not progress):
                bscene.raise_if_interrupted()  # Ctrl-C lands between frames, not after the scene
                T_wc = cams[fid]
                bscene.set_camera(T_wc)
                t0 = time.perf_counter()
                rgb = bscene.render_rgb()
                t1 = time.perf_counter()
                depth, inst = bscene.render_ground_truth()
                if cfg.render.depth_noise is not None:  # the measured depth; masks and poses stay exact
                    depth = add_depth_noise(depth, K, cfg.render.depth_noise, frame_rng(seed, fid))
                t2 = time.perf_counter()
                T_cw = invert_T(T_wc)
                writer.write_frame(fid, rgb, depth, inst, K, T_wc,
                                   [{"obj_id": li + 1, "inst_id": i, "T_cam_model": T_cw @ T} for i, li, T in instances])
                timings["render_image"] += t1 - t0
                timings["render_gt"] += t2 - t1
                timings["write"] += time.perf_counter() - t2
            device = bscene.device
        writer.finish({
            "scene_index": index, "seed": seed,
            "instances": {str(i): li + 1 for i, li, _ in instances},
            "object_names": {str(i): library[li].name for i, li, _ in instances},
            "object_poses_world": {str(i): np.asarray(T).tolist() for i, _, T in instances},
            "removed_objects": [library[chosen[j]].name for j in drop.removed],
            "physics": {"attempts": drop.attempts, "steps": drop.steps, "max_penetration_m": drop.max_penetration_m},
            "table_plane": [0.0, 0.0, 1.0, 0.0],
            "orbit": orbit, "frame_step": cfg.frame_step, "appearance": appearance, "renderer": device,
        })
    return timings
