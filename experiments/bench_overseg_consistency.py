"""Consistency of the over-segmentation under sub-voxel shifts: the same cloud, translated by a few
offsets smaller than a voxel, should be cut into the same supervoxels and LCCP segments.

    .venv/bin/python experiments/bench_overseg_consistency.py --recon OUT/work/_stages/tiny/recon \\
        [--out experiments/results/overseg_consistency.json] [--shifts 5]

Clouds: the analytic scene of ``bench/bench_overseg.py`` (:func:`selfseg.analytic.scene_meshes`; ray-cast, 1 mm
noise, one point per 5 mm cell: coordinates off any lattice) and every reconstructed TSDF cloud under ``--recon``
(``recon`` stage folders of ``evaluate``/``evaluate3d``: 5 mm TSDF voxels, so two of each point's three coordinates lie on
the 5 mm lattice). Each cloud is over-segmented at offset 0 and at ``--shifts`` − 1 random offsets
(uniform in [0, 1) voxel per axis, seed 0), with the grids anchored at the world origin (the former
code) and on the cloud (:func:`selfseg.method.supervoxels.grid_origin`). Reported per cloud and anchor:
voxels, supervoxels and LCCP segments per shift, the unlabelled-point fraction, and the adjusted Rand
index (ARI) of the LCCP segmentations (and of the supervoxels) over all pairs of shifts.
"""
from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import numpy as np

from selfseg.analytic import fused_cloud, scene_meshes
from selfseg.eval.points import adjusted_rand_index
from selfseg.eval.provenance import machine
from selfseg.fileio import write_json
from selfseg.method.lccp import LCCPConfig, lccp_from_supervoxels
from selfseg.method.recon_stage import CLOUD_NPZ, load_recon
from selfseg.method.supervoxels import supervoxel_clustering

ANCHORS = ("world", "cloud")


def segment(P, N, C, cfg: LCCPConfig, anchor: str):
    """(supervoxels, LCCP label per point (−1 = unlabelled)) with the grids anchored as given."""
    sv = supervoxel_clustering(P, N, C, cfg.voxel_resolution_m, cfg.seed_resolution_m, cfg.color_importance,
                               cfg.spatial_importance, cfg.normal_importance, anchor=anchor)
    seg = lccp_from_supervoxels(sv, cfg)
    return sv, np.where(sv.point_label >= 0, seg[np.maximum(sv.point_label, 0)], -1)


def consistency(P, N, C, offsets, cfg: LCCPConfig) -> dict:
    out = {}
    for anchor in ANCHORS:
        runs = [segment(P + d, N, C, cfg, anchor) for d in offsets]
        seg_ari = [adjusted_rand_index(a[1], b[1]) for a, b in itertools.combinations(runs, 2)]
        sv_ari = [adjusted_rand_index(a[0].point_label, b[0].point_label) for a, b in itertools.combinations(runs, 2)]
        out[anchor] = {
            "voxels": [int(sv.point_voxel.max() + 1) for sv, _ in runs],
            "supervoxels": [int(sv.n) for sv, _ in runs],
            "segments": [int(len(np.unique(lab[lab >= 0]))) for _, lab in runs],
            "unlabelled_fraction": [round(float((lab < 0).mean()), 5) for _, lab in runs],
            "segment_ari_mean": round(float(np.mean(seg_ari)), 4), "segment_ari_min": round(float(np.min(seg_ari)), 4),
            "supervoxel_ari_mean": round(float(np.mean(sv_ari)), 4),
            "supervoxel_ari_min": round(float(np.min(sv_ari)), 4),
        }
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recon", type=Path, help="folder of recon stage folders (one per video)")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "overseg_consistency.json"))
    ap.add_argument("--shifts", type=int, default=5, help="offsets per cloud, the first being 0")
    args = ap.parse_args(argv)
    cfg = LCCPConfig()
    v = cfg.voxel_resolution_m
    offsets = np.vstack([np.zeros(3), np.random.default_rng(0).uniform(0, v, (args.shifts - 1, 3))])
    clouds = []
    P, N, _ = fused_cloud(scene_meshes(), n_views=32, grid_m=v, width=320, height=240, fx=280.0, radius=0.7)
    clouds.append(("analytic", P, N, None))
    if args.recon is not None:
        for d in sorted(p for p in args.recon.iterdir() if (p / CLOUD_NPZ).is_file()):
            r = load_recon(d)
            clouds.append((f"tsdf:{d.name}", np.asarray(r.points_w, np.float64), np.asarray(r.normals_w, np.float64),
                           np.asarray(r.colors, np.float64) * 255.0))
    results = []
    for name, P, N, C in clouds:
        r = {"name": name, "points": int(len(P)), **consistency(P, N, C, offsets, cfg)}
        results.append(r)
        for a in ANCHORS:
            x = r[a]
            print(f"{name:12s} {a:5s}  voxels {x['voxels']}  segments {x['segments']}  unlabelled max "
                  f"{max(x['unlabelled_fraction']):.4f}  segment ARI mean {x['segment_ari_mean']:.3f} min "
                  f"{x['segment_ari_min']:.3f}  supervoxel ARI mean {x['supervoxel_ari_mean']:.3f}")
    summary = {a: {k: round(float(np.mean([r[a][k] for r in results if r["name"].startswith("tsdf")])), 4)
                   for k in ("segment_ari_mean", "segment_ari_min", "supervoxel_ari_mean")}
               for a in ANCHORS} if len(results) > 1 else {}
    if summary:
        print("TSDF clouds, mean over videos: " + "; ".join(f"{a}: {summary[a]}" for a in ANCHORS))
    write_json(args.out, {"lccp": {"voxel_resolution_m": v, "seed_resolution_m": cfg.seed_resolution_m},
                          "offsets_m": offsets.tolist(), "clouds": results, "tsdf_summary": summary,
                          "machine": machine()})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
