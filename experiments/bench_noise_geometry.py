"""Diagnostic, not a test: which part of the depth-noise model moves the geometric baselines on piles?

    .venv/bin/python experiments/bench_noise_geometry.py --data DIR [--lccp-cache DIR] [--stride 10]
                                                        [--json experiments/results/noise_geometry.json]

The structured-light model (``selfseg.generate.depth_noise``) is applied afterwards to the exact depth of every
``--stride``-th frame of every video of a development dataset, in variants that share their random draws
(:data:`VARIANTS`). Per variant: depth-clustering and lccp-frame IoU on the ground-truth foreground, the share of
touching instance pairs each joins, and the share of contact pixels left without depth.
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from common import joined, save_rows, touching_pairs

from selfseg.baselines.lccp_frame import LCCPFrameConfig, lccp_frame_labels
from selfseg.baselines.simple import DepthClusteringConfig, cluster_depth
from selfseg.dataset import Dataset
from selfseg.eval.folds import select_test_frames
from selfseg.eval.metrics import frame_metrics
from selfseg.generate.depth_noise import DepthNoiseConfig, add_depth_noise, frame_rng

KINECT = DepthNoiseConfig()
VARIANTS: dict[str, DepthNoiseConfig | None] = {
    "exact": None,
    "full": KINECT,
    "no-dropout": replace(KINECT, edge_dropout=0.0, grazing_start_deg=89.99, grazing_full_deg=90.0,
                          projector_shadow=False),
    "dropout-only": replace(KINECT, disparity_sigma_px=0.0, disparity_step_px=0.0, lateral_sigma_px=0.0),
    # the full model less one kind of dropout each
    "no-edge-dropout": replace(KINECT, edge_dropout=0.0),
    "no-grazing-dropout": replace(KINECT, grazing_start_deg=89.99, grazing_full_deg=90.0),
    "no-projector-shadow": replace(KINECT, projector_shadow=False),
}
MIN_CONTACT_PX = 20


def contact_band(gt: np.ndarray, pairs: list[tuple[int, int]]) -> np.ndarray:
    """Pixels of each touching instance within 2 px (8-connected dilation by 2) of its touching neighbour."""
    kernel = np.ones((5, 5), np.uint8)
    band = np.zeros(gt.shape, bool)
    for a, b in pairs:
        for x, y in ((a, b), (b, a)):
            band |= (gt == x) & cv2.dilate((gt == y).astype(np.uint8), kernel).astype(bool)
    return band


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="development dataset with exact depth")
    p.add_argument("--lccp-cache", help="folder of lccp-frame labels on the exact depth (lccp-<video>-<frame>.npy)")
    p.add_argument("--stride", type=int, default=10)
    p.add_argument("--json", default="experiments/results/noise_geometry.json")
    args = p.parse_args(argv)
    ds = Dataset(args.data)
    dc_cfg, lccp_cfg = DepthClusteringConfig(), LCCPFrameConfig()
    acc = {v: {"dc_iou": [], "lccp_iou": [], "dc_joined": [], "lccp_joined": [], "band_missing": [], "fg_missing": []}
           for v in VARIANTS}
    t0 = time.perf_counter()
    for vid in ds.video_ids:
        video = ds.labeled(vid)
        for f in select_test_frames(video.frame_ids, args.stride, None):
            gt = video.inst(f).astype(np.int64)
            fg = gt > 0
            if not fg.any():
                continue
            clean, K = video.depth_m(f), video.K(f)
            pairs = touching_pairs(gt, MIN_CONTACT_PX)
            band = contact_band(gt, pairs)
            for name, cfg in VARIANTS.items():
                depth = clean if cfg is None else add_depth_noise(clean, K, cfg, frame_rng(int(vid), f))
                cache = Path(args.lccp_cache) / f"lccp-{vid}-{f:06d}.npy" if args.lccp_cache and cfg is None else None
                if cache is not None and cache.is_file():
                    lccp = np.load(cache)
                else:
                    lccp = lccp_frame_labels(depth, K, fg, lccp_cfg).astype(np.int64)
                dc = cluster_depth(depth, K, fg, dc_cfg).astype(np.int64)
                a = acc[name]
                a["dc_iou"].append(frame_metrics(dc, gt)["IoU"])
                a["lccp_iou"].append(frame_metrics(lccp, gt)["IoU"])
                a["dc_joined"] += [joined(dc, gt, x, y) for x, y in pairs]
                a["lccp_joined"] += [joined(lccp, gt, x, y) for x, y in pairs]
                a["band_missing"].append((np.count_nonzero(band & (depth <= 0)), np.count_nonzero(band)))
                a["fg_missing"].append((np.count_nonzero(fg & (depth <= 0)), np.count_nonzero(fg)))
        print(f"video {vid}: {len(acc['exact']['dc_iou'])} frames ({time.perf_counter() - t0:.0f} s)", flush=True)
    rows = []
    for name, a in acc.items():
        row = {"data": args.data, "dataset_hash": ds.content_hash(), "stride": args.stride, "variant": name,
               "frames": len(a["dc_iou"]), "touching_pairs": len(a["dc_joined"]),
               "dc_iou": round(float(np.mean(a["dc_iou"])), 4), "lccp_iou": round(float(np.mean(a["lccp_iou"])), 4),
               "dc_joined": round(float(np.mean(a["dc_joined"])), 4),
               "lccp_joined": round(float(np.mean(a["lccp_joined"])), 4),
               "contact_missing": round(sum(m for m, _ in a["band_missing"]) / max(1, sum(n for _, n in a["band_missing"])), 4),
               "fg_missing": round(sum(m for m, _ in a["fg_missing"]) / max(1, sum(n for _, n in a["fg_missing"])), 4),
               "wall_s": round(time.perf_counter() - t0, 1)}
        print({k: v for k, v in row.items() if k not in ("data", "dataset_hash")}, flush=True)
        rows.append(row)
    save_rows(args.json, rows, lambda r: (r["dataset_hash"], r["stride"], r["variant"]),
              "geometric baselines under parts of the depth-noise model (experiments/bench_noise_geometry.py)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
