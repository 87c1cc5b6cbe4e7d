"""Benchmark of the recon stage: tracking + TSDF fusion, background removal, foreground masks.

    .venv/bin/python bench/bench_recon.py [--frames 200] [--data DATASET [--videos 2]]
                                         [--out bench/results/recon.json]

Without ``--data`` the video is analytic: a box, a cylinder and a bowl on a table, ray-cast at
320×240 (fx = 300) along an orbit of ``--frames`` frames at 1.5° per frame. With ``--data`` the
first ``--videos`` videos of a generated dataset are used. For each video: the whole stage with
estimated poses (seconds, ms per frame for tracking + fusion and where the time goes), pose
drift against the ground truth (ATE, final-frame error), the fused surface's distance to the
true surface (analytic scene only), and the IoU of the projected foreground masks with the true
object masks (every 10th frame). The ground-truth-pose ablation is timed alongside.
Wall-clock times depend on the machine's load (recorded); the process CPU time is reported too.
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
from common import bench_parser, write_result

from selfseg.analytic import bowl, box, cylinder, make_dataset
from selfseg.dataset import Dataset
from selfseg.method.background import BackgroundConfig
from selfseg.method.recon_stage import load_recon, run_recon_stage
from selfseg.method.reconstruct import ReconConfig, trajectory_error
from selfseg.stages import StageCache

OBJECTS = [(box((0.08, 0.08, 0.08), (-0.08, 0.0, 0.04)), 1), (cylinder(0.04, 0.1, (0.07, 0.04, 0.05)), 2),
           (bowl(center=(0.02, -0.1, 0)), 3)]


def surface_error_mm(points_w: np.ndarray, T_align: np.ndarray) -> dict:
    """Distance (mm) of fused object points, mapped into the dataset world, to the analytic meshes."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    for m, _ in OBJECTS:
        scene.add_triangles(o3d.core.Tensor(np.asarray(m.vertices, np.float32)),
                            o3d.core.Tensor(np.asarray(m.faces, np.uint32)))
    p = points_w @ T_align[:3, :3].T + T_align[:3, 3]
    d = scene.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy() * 1000
    return {"median": round(float(np.median(d)), 2), "p90": round(float(np.percentile(d, 90)), 2)}


def bench_video(ds: Dataset, vid: str, cache_root: Path, analytic: bool) -> dict:
    gt = ds.labeled(vid)
    out = {"video_id": vid, "frames": len(gt.frame_ids), "size": [gt.width, gt.height]}
    for mode, cfg in (("estimated", ReconConfig()), ("gt_poses", ReconConfig(use_gt_poses=True))):
        video = ds.video(vid, poses_given=cfg.use_gt_poses)
        t0, c0 = time.perf_counter(), time.process_time()
        stage = load_recon(run_recon_stage(video, StageCache(cache_root / mode), cfg, BackgroundConfig(),
                                           progress=False))
        seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
        t = stage.report["timings_s"]
        fids = [f for f in video.frame_ids if f in stage.T_world_cam]
        T_est = np.stack([stage.T_world_cam[f] for f in fids])
        T_ref = np.stack([gt.T_world_cam(f) for f in fids])
        ious = []
        for f in fids[::10]:
            fg, true = stage.fg_mask(f), gt.inst(f) > 0
            ious.append((fg & true).sum() / max((fg | true).sum(), 1))
        res = {"stage_s": round(seconds, 2), "stage_cpu_s": round(cpu, 2), "timings_s": t,
               "track_fuse_ms_per_frame": round(1000 * (t.get("track_s", 0) + t.get("model_s", 0) + t["integrate_s"])
                                                / len(fids), 1),
               "tracking_failures": stage.report["tracking_failures"],
               "points_fused": stage.report["points_fused"], "points_kept": stage.report["points_kept"],
               "drift": {k: round(v, 4) for k, v in trajectory_error(T_est, T_ref).items()},
               "fg_iou_mean": round(float(np.mean(ious)), 4), "fg_iou_min": round(float(np.min(ious)), 4)}
        if analytic:
            res["object_surface_error_mm"] = surface_error_mm(stage.points_w, T_ref[0] @ np.linalg.inv(T_est[0]))
        out[mode] = res
        print(f"{vid} {mode}: {seconds:.1f} s ({cpu:.1f} s CPU), {res['track_fuse_ms_per_frame']} ms/frame track+fuse, "
              f"ATE {res['drift']['ate_rmse_m'] * 1000:.1f} mm, fg IoU {res['fg_iou_mean']:.3f}", flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser(__doc__, "recon.json")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--data", type=Path, help="a generated dataset instead of the analytic video")
    ap.add_argument("--videos", type=int, default=2)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if args.data is None:
            t0 = time.perf_counter()
            root = make_dataset(tmp / "data", [OBJECTS], n_frames=args.frames, width=320, height=240, fx=300.0,
                                arc_deg=1.5 * args.frames)
            print(f"analytic video written in {time.perf_counter() - t0:.1f} s", flush=True)
            ds, vids = Dataset(root), None
        else:
            ds = Dataset(args.data)
            vids = ds.video_ids[:args.videos]
        results = [bench_video(ds, vid, tmp / "cache", args.data is None) for vid in (vids or ds.video_ids)]
    write_result(args.out, {"benchmark": "recon", "data": str(args.data) if args.data else
                            f"analytic orbit, {args.frames} frames at 1.5°/frame, 320x240",
                            "config": {"recon": "ReconConfig()", "background": "BackgroundConfig()"},
                            "videos": results})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
