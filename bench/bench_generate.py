"""Benchmark of scene generation: seconds per frame and preset wall times -> bench/results/generate.json.

Measures, on this machine:
* seconds per frame (median over a few frames of one physics-dropped 8-object scene) for the
  Cycles and Workbench renderers at 320×240 and 640×480, split into the image pass and the
  ground-truth pass, as wall time and as process CPU time (all threads; on a shared machine the
  CPU time / cores is the contention-free estimate);
* the wall time of the ``tiny`` preset (and of ``small`` with --small; otherwise it is
  extrapolated from the per-frame and per-scene costs, and the JSON says so);
* an estimate of the ``paper-synthetic`` preset's total time.

Usage: .venv/bin/python bench/bench_generate.py [--frames 3] [--small] [--out bench/results/generate.json]
"""
from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np
from common import bench_parser, write_result

from selfseg.generate.cli import main as generate_main
from selfseg.generate.physics import drop_objects
from selfseg.generate.presets import preset_config
from selfseg.generate.render import BlenderScene, RenderConfig, intrinsics, sample_appearance
from selfseg.generate.scene import camera_orbit, load_library

RESOLUTIONS = [(320, 240), (640, 480)]


def bench_frames(renderer: str, width: int, height: int, n_frames: int, library, poses, **render) -> dict:
    """Median per-frame seconds (wall and CPU) of the image and ground-truth passes."""
    cfg = preset_config("small", width=width, height=height, render={"renderer": renderer, **render})
    rng = np.random.default_rng(0)
    objects = [(k + 1, library[i], T) for k, (i, T) in enumerate(poses.items())]
    cams, _ = camera_orbit(cfg.orbit, n_frames + 1, np.array([0.0, 0.0, 0.03]), rng)
    rows = []
    t0 = time.perf_counter()
    with BlenderScene(objects, sample_appearance(rng), width, height, intrinsics(width, height, cfg.orbit.hfov_deg),
                      cfg.render) as scene:
        setup = time.perf_counter() - t0
        for i, T in enumerate(cams):
            scene.set_camera(T)
            w0, c0 = time.perf_counter(), time.process_time()
            scene.render_rgb()
            w1, c1 = time.perf_counter(), time.process_time()
            scene.render_ground_truth()
            w2, c2 = time.perf_counter(), time.process_time()
            if i > 0:  # the first frame compiles shaders and loads kernels
                rows.append((w1 - w0, c1 - c0, w2 - w1, c2 - c1))
        device = scene.device
    r = np.median(np.array(rows), axis=0)
    return {"renderer": renderer, **render, "device": device, "resolution": [width, height], "frames": len(rows),
            "setup_s": round(setup, 3), "image_wall_s": round(r[0], 3), "image_cpu_s": round(r[1], 3),
            "gt_wall_s": round(r[2], 3), "gt_cpu_s": round(r[3], 3), "frame_wall_s": round(r[0] + r[2], 3),
            "frame_cpu_s": round(r[1] + r[3], 3)}


SWEEP = [{"samples": 64, "denoise": True}, {"samples": 16, "denoise": False}, {"samples": 8, "denoise": True},
         {"samples": 4, "denoise": True}, {"samples": 2, "denoise": True}, {"samples": 4, "denoise": True, "max_bounces": 2}]


def cycles_sweep(library, poses, width: int = 320, height: int = 240) -> list[dict]:
    """Cycles settings on one view: image-pass seconds (wall, CPU) and PSNR (dB) against the
    64-sample denoised image (SWEEP[0]), the reference."""
    cfg = preset_config("small", width=width, height=height)
    rng = np.random.default_rng(0)
    objects = [(k + 1, library[i], T) for k, (i, T) in enumerate(poses.items())]
    cam = camera_orbit(cfg.orbit, 1, np.array([0.0, 0.0, 0.03]), rng)[0][0]
    appearance = sample_appearance(rng)
    rows, ref = [], None
    for kw in SWEEP:
        render = RenderConfig(**{**vars(cfg.render), **kw})
        with BlenderScene(objects, appearance, width, height, intrinsics(width, height, cfg.orbit.hfov_deg),
                          render) as scene:
            scene.set_camera(cam)
            scene.render_rgb()  # warm-up
            w0, c0 = time.perf_counter(), time.process_time()
            img = scene.render_rgb().astype(np.float64)
            wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        ref = img if ref is None else ref
        mse = float(np.mean((img - ref) ** 2))
        rows.append({**kw, "max_bounces": render.max_bounces, "image_wall_s": round(wall, 3),
                     "image_cpu_s": round(cpu, 3), "psnr_vs_reference_db": None if mse == 0 else round(10 * np.log10(255**2 / mse), 2)})
    return rows


def bench_preset(preset: str, tmp: Path) -> dict:
    out = tmp / preset
    w0, c0 = time.perf_counter(), time.process_time()
    rc = generate_main(["--preset", preset, "--out", str(out), "--quiet"])
    if rc != 0:
        raise SystemExit(f"generate_scenes --preset {preset} failed with exit code {rc}")
    return {"wall_s": round(time.perf_counter() - w0, 1), "cpu_s": round(time.process_time() - c0, 1)}


def estimate(preset: str, per_frame: float, per_scene: float, **overrides) -> dict:
    """Projected seconds for a preset: frames × s/frame + scenes × per-scene overhead."""
    cfg = preset_config(preset, **overrides)
    frames = cfg.scenes * len(cfg.frame_ids)
    return {"scenes": cfg.scenes, "frames": frames, "resolution": [cfg.width, cfg.height], "frame_step": cfg.frame_step,
            "estimated_s": round(frames * per_frame + cfg.scenes * per_scene, 0)}


def main() -> None:
    ap = bench_parser(__doc__, "generate.json")
    ap.add_argument("--frames", type=int, default=3, help="frames timed per renderer and resolution (after a warm-up)")
    ap.add_argument("--small", action="store_true", help="also run the small preset (about 10+ minutes)")
    args = ap.parse_args()

    load_start = os.getloadavg()
    library = load_library(preset_config("small"))
    t0 = time.perf_counter()
    drop = drop_objects(library[:8], seed=0)
    physics_s = time.perf_counter() - t0
    poses = drop.poses

    per_frame = []
    for renderer in ("workbench", "cycles"):
        for w, h in RESOLUTIONS:
            res = bench_frames(renderer, w, h, args.frames, library, poses)
            print(res, flush=True)
            per_frame.append(res)

    sweep = cycles_sweep(library, poses)
    print(sweep, flush=True)

    presets = {}
    with tempfile.TemporaryDirectory(prefix="bench_generate_") as tmp:
        presets["tiny"] = bench_preset("tiny", Path(tmp))
        print("tiny", presets["tiny"], flush=True)
        if args.small:
            presets["small"] = bench_preset("small", Path(tmp))
            print("small", presets["small"], flush=True)

    def frame_s(renderer, w, key="frame_wall_s"):
        return next(r[key] for r in per_frame if r["renderer"] == renderer and r["resolution"][0] == w)

    per_scene = physics_s + max(r["setup_s"] for r in per_frame)
    ncpu = os.cpu_count() or 1
    estimates = {
        "paper-synthetic": estimate("paper-synthetic", frame_s("cycles", 640), per_scene),
        "paper-synthetic_frame_step_4": estimate("paper-synthetic", frame_s("cycles", 640), per_scene, frame_step=4),
        "paper-synthetic_cpu_bound": {**estimate("paper-synthetic", frame_s("cycles", 640, "frame_cpu_s") / ncpu,
                                                 per_scene),
                                      "basis": "CPU seconds per frame / cores: the time on an otherwise idle machine"},
    }
    if not args.small:
        estimates["small"] = {**estimate("small", frame_s("cycles", 320), per_scene),
                              "basis": "not run (use --small): extrapolated from cycles 320x240 s/frame"}
    result = {"physics_8_objects_s": round(physics_s, 2), "per_frame": per_frame, "cycles_settings_320x240": sweep,
              "presets": presets,
              "estimates": estimates, "render_config": vars(RenderConfig())}
    write_result(args.out, result, load_start)


if __name__ == "__main__":
    main()
