"""Diagnostic: does LCCP join touching objects because of their shapes or because of the reconstruction?

    .venv/bin/python experiments/bench_touching_pairs.py --data runs/clut7/data --config configs/ours-calibrated.yaml \
        --stages runs/clut7/results/work/_stages/<dataset folder> [--videos 000000,...] \
        [--json experiments/results/touching_pairs.json]

``--stages``: the per-video stage folder of an ``evaluate3d`` run on DATA (it holds ``recon/<video>``). For each
touching pair of ground-truth objects (meshes within 5 mm, :func:`selfseg.eval.datastats.touching_pairs`), LCCP
with the config's settings runs on four clouds of the scene:

- ``gt_geometry``: perfect geometry, ray-cast from the GT meshes at their GT poses through the video's own
  cameras (every FRAME_STRIDE-th frame), the meshes' normals, one point per reconstruction voxel;
- ``gt_points_fitted_normals``: the same points with normals fitted to their neighbours (3 voxels), the share
  normal estimation adds;
- ``recon_points_gt_normals``: the reconstruction's points (aligned to the dataset's world frame) with the nearest
  GT triangle's normal, the share the fused point positions add;
- ``recon``: the reconstruction as the pipeline over-segments it.

A pair is *joined* when one segment holds at least JOIN_SHARE of both objects' contact points (each object's
points within CONTACT_M of the other's); pairs with fewer than 5 contact points on a side are not comparable.
Each cloud's LCCP segmentation is also scored as a whole (P, R, IoU over its points, per video, then the mean:
LCCP alone, without SymSeg or the pipeline's pruning of small segments, so not Table II's LCCP row).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from selfseg.config import load_config
from selfseg.dataset import Dataset
from selfseg.eval.datastats import touching_pairs
from selfseg.eval.metrics import segment_metrics
from selfseg.eval.points import gt_point_labels, gt_scene
from selfseg.eval.provenance import machine
from selfseg.eval.table2 import alignment
from selfseg.fileio import write_json
from selfseg.poses import transform_points
from selfseg.method.lccp import lccp_segment
from selfseg.method.pipeline import OursConfig
from selfseg.method.recon_stage import load_recon

FRAME_STRIDE = 2
CONTACT_M = 0.01  # points of an object within this of the other object are its contact region
JOIN_SHARE = 0.5  # a pair is joined when one segment holds this share of both objects' contact points
VARIANTS = ("gt_geometry", "gt_points_fitted_normals", "recon_points_gt_normals", "recon")  # the clouds compared


def gt_cloud(ds: Dataset, vid: str, voxel_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points N×3 world m, outward unit normals N×3, instance id N) ray-cast from the GT meshes through the
    video's cameras (every FRAME_STRIDE-th frame), one point per voxel (the first hit's)."""
    lab = ds.labeled(vid)
    scene = gt_scene(ds, vid)
    pts, nrm, ids = [], [], []
    for fid in lab.frame_ids[::FRAME_STRIDE]:
        K, T = lab.K(fid), lab.T_world_cam(fid)
        h, w = lab.rgb(fid).shape[:2]
        depth, inst, n_cam = scene.render(K, T, w, h)
        v, u = np.nonzero(inst > 0)
        z = depth[v, u]
        p_cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], 1)
        R, t = T[:3, :3], T[:3, 3]
        p_w = p_cam @ R.T + t
        n_w = n_cam[v, u] @ R.T
        flip = (n_w * (p_w - t)).sum(1) > 0  # face the camera
        n_w[flip] *= -1
        pts.append(p_w), nrm.append(n_w), ids.append(inst[v, u].astype(np.int64))
    p, n, i = np.concatenate(pts), np.concatenate(nrm), np.concatenate(ids)
    key = np.floor(p / voxel_m).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    first.sort()
    return p[first], n[first] / np.linalg.norm(n[first], axis=1, keepdims=True), i[first]


def mesh_normals(scene, points: np.ndarray, like: np.ndarray) -> np.ndarray:
    """Unit normal of the nearest GT triangle at each world point, signed to agree with ``like`` (N×3)."""
    import open3d as o3d

    o3s, _ = scene._o3d_scene()
    n = o3s.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))["primitive_normals"].numpy()
    n = n.astype(np.float64) / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    n[(n * like).sum(1) < 0] *= -1
    return n


def pca_normals(points: np.ndarray, like: np.ndarray, radius_m: float) -> np.ndarray:
    """Normals of local planes fitted to the points within ``radius_m`` (open3d), signed to agree with ``like``."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=60))
    n = np.asarray(pc.normals)
    n[(n * like).sum(1) < 0] *= -1
    return n


def joined(labels: np.ndarray, gt: np.ndarray, points: np.ndarray, a: int, b: int) -> dict:
    """Whether LCCP joined objects a and b at their contact: the contact points of each (within CONTACT_M of the
    other object's points) and the share of both held by the single segment holding most of them."""
    from scipy.spatial import cKDTree

    pa, pb = np.flatnonzero(gt == a), np.flatnonzero(gt == b)
    if len(pa) == 0 or len(pb) == 0:
        return {"contact_points": 0, "joined": None}
    da = cKDTree(points[pb]).query(points[pa])[0]
    db = cKDTree(points[pa]).query(points[pb])[0]
    ca, cb = pa[da <= CONTACT_M], pb[db <= CONTACT_M]
    if len(ca) < 5 or len(cb) < 5:
        return {"contact_points": int(len(ca) + len(cb)), "joined": None}
    la, lb = labels[ca], labels[cb]
    best = 0.0
    for s in np.unique(np.concatenate([la, lb])):
        if s < 0:
            continue
        best = max(best, min((la == s).mean(), (lb == s).mean()))
    return {"contact_points": int(len(ca) + len(cb)), "share": round(float(best), 3), "joined": bool(best >= JOIN_SHARE)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--data", required=True)
    p.add_argument("--config", required=True)
    p.add_argument("--stages", required=True, help="the stage folder holding recon/<video>")
    p.add_argument("--videos", default="")
    p.add_argument("--json", default="experiments/results/touching_pairs.json")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="config override, as evaluate's (e.g. overseg.lccp.seed_resolution_m=0.02)")
    p.add_argument("--variants", default=",".join(VARIANTS),
                   help=f"clouds to segment, comma-separated (default all: {','.join(VARIANTS)})")
    args = p.parse_args(argv)
    variants = args.variants.split(",")
    if set(variants) - set(VARIANTS) or not {"gt_geometry", "recon"} <= set(variants):
        p.error(f"--variants: gt_geometry and recon, and any of {', '.join(VARIANTS)}")
    ds = Dataset(args.data)
    cfg = load_config(OursConfig, args.config, args.overrides)
    vids = args.videos.split(",") if args.videos else ds.video_ids
    rows, videos = [], []
    for vid in vids:
        scene = gt_scene(ds, vid)
        pairs = touching_pairs(scene)
        rec = load_recon(Path(args.stages) / "recon" / vid)
        T, _ = alignment(rec, ds.labeled(vid))  # the reconstruction's world → the dataset's
        r_pts, r_nrm = transform_points(rec.points_w, T), rec.normals_w @ T[:3, :3].T
        r_gt = gt_point_labels(r_pts, ds, vid)
        r_lab = lccp_segment(r_pts, r_nrm, rec.colors, cfg.overseg.lccp)
        g_pts, g_nrm, g_gt = gt_cloud(ds, vid, cfg.recon.voxel_size_m)
        g_lab = lccp_segment(g_pts, g_nrm, None, cfg.overseg.lccp)
        clouds = {"recon": (r_lab, r_gt, r_pts), "gt_geometry": (g_lab, g_gt, g_pts)}
        # the two halves of the difference: GT points with fitted normals, reconstructed points with GT normals
        radius = 3 * cfg.recon.voxel_size_m
        if "gt_points_fitted_normals" in variants:
            clouds["gt_points_fitted_normals"] = (
                lccp_segment(g_pts, pca_normals(g_pts, g_nrm, radius), None, cfg.overseg.lccp), g_gt, g_pts)
        if "recon_points_gt_normals" in variants:
            clouds["recon_points_gt_normals"] = (
                lccp_segment(r_pts, mesh_normals(scene, r_pts, r_nrm), rec.colors, cfg.overseg.lccp), r_gt, r_pts)
        scores = {k: segment_metrics(lab + 1, gt) for k, (lab, gt, _) in clouds.items()}  # −1 (none) → 0
        videos.append({"video": vid, "touching_pairs": len(pairs),
                       **{k: {m: round(float(v[m]), 4) for m in ("P", "R", "IoU")} for k, v in scores.items()}})
        for a, b in pairs:
            row = {"video": vid, "pair": [int(a), int(b)],
                   **{k: joined(lab, gt, pts, a, b) for k, (lab, gt, pts) in clouds.items()}}
            rows.append(row)
            print(json.dumps(row), flush=True)
    both = [r for r in rows if r["recon"]["joined"] is not None and r["gt_geometry"]["joined"] is not None]
    tab = {(g, r): sum(1 for x in both if x["gt_geometry"]["joined"] == g and x["recon"]["joined"] == r)
           for g in (False, True) for r in (False, True)}
    print(f"pairs {len(rows)}, comparable {len(both)}")
    print(f"  separate on GT geometry and on the reconstruction: {tab[False, False]}")
    print(f"  separate on GT geometry, joined on the reconstruction: {tab[False, True]}  (the reconstruction's fault)")
    print(f"  joined on GT geometry, separate on the reconstruction: {tab[True, False]}")
    print(f"  joined on both (the shapes' convex contact): {tab[True, True]}")
    for k in variants:
        ok = [r[k]["joined"] for r in rows if r[k]["joined"] is not None]
        print(f"  {k}: joined {sum(ok)} of {len(ok)} ({100 * sum(ok) / max(len(ok), 1):.0f} %)")
    segmentation = {k: {m: round(float(np.mean([v[k][m] for v in videos])), 4) for m in ("P", "R", "IoU")}
                    for k in variants}
    for k, v in segmentation.items():
        print(f"  {k}: LCCP P {v['P']:.3f} R {v['R']:.3f} IoU {v['IoU']:.3f} (mean over videos, every point)")
    joined_share = {k: [r[k]["joined"] for r in rows if r[k]["joined"] is not None] for k in variants}
    write_json(args.json, {"what": "LCCP on touching object pairs: ground-truth geometry against the reconstruction "
                                   "(experiments/bench_touching_pairs.py)",
                           "data": str(Path(args.data).resolve()), "dataset_hash": ds.content_hash(),
                           "config": args.config, "overrides": args.overrides, "machine": machine(), "n_pairs": len(rows),
                           "joined": {k: {"joined": sum(v), "comparable": len(v)} for k, v in joined_share.items()},
                           "gt_vs_recon": {f"gt_{'joined' if g else 'separate'}_recon_{'joined' if r else 'separate'}": v
                                           for (g, r), v in tab.items()},
                           "segmentation": segmentation, "videos": videos, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
