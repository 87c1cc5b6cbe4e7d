"""Benchmark of the 3D over-segmentation: seconds for LCCP, SymSeg and the segment graph per scene.

    .venv/bin/python bench/bench_overseg.py [--out bench/results/overseg.json] [--repeats 2]

The scene is analytic (:func:`selfseg.analytic.scene_meshes`): 9 objects (boxes, cylinders, bowls, a mug) on a
table, some touching, ray-cast from 32 views all around with 1 mm depth noise and thinned to one point per grid
cell (5, 2.5 and 1.5 mm: about 16k to 180k points), table removed. Also reported: how many of the
objects a segment recovers at point IoU ≥ 0.8 (the mug with its handle is one object), also
with LCCP's sanity criterion off (PCL's example default). Timings exclude numba's one-off compilation (reported separately); the best of ``--repeats`` runs is kept.
"""
from __future__ import annotations

import time

import numpy as np
from common import bench_parser, write_result

from selfseg.analytic import fused_cloud, scene_meshes
from selfseg.method.lccp import LCCPConfig, lccp_segment
from selfseg.method.overseg import OversegConfig, fuse_symmetries, oversegment, prune_small
from selfseg.method.segment_graph import build_segment_graph
from selfseg.method.symseg import SymSegConfig, detect_rotational_symmetries


def objects_recovered(labels: np.ndarray, gt: np.ndarray, min_iou: float = 0.8) -> int:
    """Ground-truth objects whose best-overlapping segment has point IoU ≥ ``min_iou``."""
    n = 0
    for k in np.unique(gt):
        seg = labels[gt == k]
        seg = seg[seg >= 0]
        if len(seg):
            s = np.bincount(seg).argmax()
            inter = np.sum((labels == s) & (gt == k))
            n += inter / np.sum((labels == s) | (gt == k)) >= min_iou
    return int(n)


def bench_one(P, N, gt, repeats: int) -> dict:
    lccp_cfg, sym_cfg = LCCPConfig(), SymSegConfig()
    t_lccp, t_sym, t_graph = [], [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        lab = lccp_segment(P, N, None, lccp_cfg)
        t1 = time.perf_counter()
        syms = detect_rotational_symmetries(P, N, lab, None, sym_cfg)
        final = prune_small(fuse_symmetries(lab, P, N, syms, sym_cfg), OversegConfig().min_segment_points)
        t2 = time.perf_counter()
        build_segment_graph(P, final, lccp_cfg.voxel_resolution_m)
        t3 = time.perf_counter()
        t_lccp.append(t1 - t0)
        t_sym.append(t2 - t1)
        t_graph.append(t3 - t2)
    return {"points": int(len(P)), "lccp_s": round(min(t_lccp), 3), "symseg_s": round(min(t_sym), 3),
            "graph_s": round(min(t_graph), 3), "lccp_segments": int(lab.max() + 1),
            "symmetries": len(syms), "final_segments": int(final.max() + 1),
            "pruned_fraction": round(float((final < 0).mean()), 4),
            "objects_iou80_lccp": objects_recovered(prune_small(lab, OversegConfig().min_segment_points), gt),
            "objects_iou80_lccp_symseg": objects_recovered(final, gt),
            "objects_iou80_lccp_symseg_no_sanity": objects_recovered(oversegment(
                P, N, None, None, OversegConfig(lccp=LCCPConfig(use_sanity_criterion=False))), gt)}


def main(argv=None) -> None:
    ap = bench_parser(__doc__, "overseg.json")
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args(argv)
    meshes = scene_meshes()
    t0 = time.perf_counter()
    P, N, _ = fused_cloud(meshes[:1], n_views=2)
    lccp_segment(P, N, None, LCCPConfig())  # numba compilation (cached on disk afterwards)
    compile_s = time.perf_counter() - t0
    results = []
    for grid, (w, h, fx) in ((0.005, (320, 240, 280.0)), (0.0025, (320, 240, 280.0)), (0.0015, (640, 480, 560.0))):
        P, N, gt = fused_cloud(meshes, n_views=32, grid_m=grid, width=w, height=h, fx=fx, radius=0.7)
        r = bench_one(P, N, gt, args.repeats)
        r["grid_m"] = grid
        results.append(r)
        print(f"grid {grid * 1000:.1f} mm: {r['points']} points  LCCP {r['lccp_s']:.2f} s  SymSeg {r['symseg_s']:.2f} s"
              f"  graph {r['graph_s']:.2f} s  ({r['lccp_segments']} LCCP segments, {r['symmetries']} symmetries,"
              f" {r['final_segments']} final; objects at IoU ≥ 0.8: {r['objects_iou80_lccp']} LCCP,"
              f" {r['objects_iou80_lccp_symseg']} LCCP+SymSeg of {len(meshes)};"
              f" {r['objects_iou80_lccp_symseg_no_sanity']} without the sanity criterion)")
    write_result(args.out, {"objects": len(meshes), "scenes": results,
                            "first_call_with_compile_s": round(compile_s, 2)})


if __name__ == "__main__":
    main()
