"""Diagnostic, not a test: does inference with square foreground crops (``test_square_crop``) segment as the plain
foreground crops do?

    .venv/bin/python experiments/bench_square_crop.py --data DIR --weights NET/weights.pt
        [--config configs/ours-calibrated.yaml] [--frame-step 5]
        [--json experiments/results/square_crop_agreement.json]

Square crops give every frame one input shape, so a GPU runs the network as one CUDA graph (and frames batched);
plain crops give each frame its own. The network, scale, masked background and test-time flip are the config's
(``phi1_train`` for φ1 weights, ``train`` otherwise: ``--phase``); the frames get the ground-truth foreground, as
the evaluation protocol gives it. Per frame, both paths' labels (the config's clustering, numpy) are scored against
the ground truth (the paper's IoU, as Table I) and against each other (the plain path's labels as the reference);
the embeddings' cosine similarity over the foreground is reported too. A development dataset only: this reads
ground truth.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from common import save_rows

from selfseg.config import load_config
from selfseg.dataset import Dataset
from selfseg.eval.metrics import frame_metrics
from selfseg.method.features import embed_frames, foreground_box
from selfseg.method.meanshift import cluster_frame
from selfseg.method.pipeline import OursConfig
from selfseg.method.train import load_embedding_net


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="development dataset folder")
    p.add_argument("--weights", required=True, help="an embedding network's weights.pt")
    p.add_argument("--config", default="configs/ours-calibrated.yaml")
    p.add_argument("--phase", choices=("phi1_train", "train"), default="phi1_train",
                   help="which of the config's training sections the weights were trained with")
    p.add_argument("--frame-step", type=int, default=5, help="every n-th frame of each video")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", default="experiments/results/square_crop_agreement.json")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    cfg = load_config(OursConfig, args.config)
    train = getattr(cfg, args.phase)
    if not (train.fg_crop and train.mask_background):
        p.error(f"{args.config}: {args.phase} has no foreground crop with masked background: nothing to compare")
    net = load_embedding_net(args.weights, "cpu")
    ds = Dataset(args.data)
    iou = {"plain": [], "square": []}
    agree, cos_mean, cos_p01 = [], [], []
    t0 = time.perf_counter()
    for vid in ds.video_ids:
        video = ds.labeled(vid)
        for f in video.frame_ids[::args.frame_step]:
            gt = video.inst(f).astype(np.int64)
            fg = gt > 0
            if not fg.any():
                continue
            rgb = video.rgb(f)
            box = [foreground_box(fg, train.fg_crop_margin)]
            emb = {k: embed_frames(net, [rgb], "cpu", train.image_size, box, [fg], cfg.test_flip, k == "square")[0]
                   for k in iou}
            labels = {k: cluster_frame(e.numpy(), fg, cfg.cluster) for k, e in emb.items()}
            for k in iou:
                iou[k].append(frame_metrics(labels[k], gt)["IoU"])
            agree.append(frame_metrics(labels["square"], np.where(fg, labels["plain"], 0))["IoU"])
            cos = (emb["plain"] * emb["square"]).sum(0)[torch.from_numpy(fg)]
            cos_mean.append(float(cos.mean()))
            cos_p01.append(float(torch.quantile(cos, 0.01)))
        print(f"{vid}: {len(agree)} frames, IoU plain {np.mean(iou['plain']):.4f} square "
              f"{np.mean(iou['square']):.4f}, agreement {np.mean(agree):.4f}", flush=True)
    diff = np.asarray(iou["square"]) - np.asarray(iou["plain"])
    rng = np.random.default_rng(0)
    boot = [diff[rng.integers(0, len(diff), len(diff))].mean() for _ in range(2000)]
    row = {"data": args.data, "dataset_hash": ds.content_hash(), "weights": args.weights, "config": args.config,
           "phase": args.phase, "frame_step": args.frame_step, "frames": len(agree),
           "iou_plain": round(float(np.mean(iou["plain"])), 4), "iou_square": round(float(np.mean(iou["square"])), 4),
           "iou_square_minus_plain": round(float(diff.mean()), 4),
           "iou_square_minus_plain_ci95": [round(float(q), 4) for q in np.percentile(boot, [2.5, 97.5])],
           "agreement_iou_mean": round(float(np.mean(agree)), 4),
           "agreement_iou_min": round(float(np.min(agree)), 4),
           "frames_agreement_below_0.99": int(np.sum(np.asarray(agree) < 0.99)),
           "cosine_mean": round(float(np.mean(cos_mean)), 5), "cosine_p01_mean": round(float(np.mean(cos_p01)), 5),
           "wall_s": round(time.perf_counter() - t0, 1)}
    print({k: v for k, v in row.items() if k not in ("data", "weights")})
    save_rows(args.json, [row], lambda r: (r["dataset_hash"], r["weights"], r["phase"], r["frame_step"]),
              "Square against plain foreground crops at inference (experiments/bench_square_crop.py)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
