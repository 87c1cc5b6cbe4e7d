"""Diagnostic, not a test: single-frame LCCP's segments merged by a learned embedding, on a development fold.

    .venv/bin/python experiments/bench_segment_merging.py --data DIR --fold 0 --work WORK
        --net NAME=METHOD,CONFIG,WEIGHTS [--net ...]
        [--json experiments/results/cluttered_segment_merging.json]

Per scored frame (every 10th frame, the ground-truth foreground, as the protocol scores them) of the fold's
training and test videos: lccp-frame's labels (default settings, as the confirmations run it; cached in WORK), the
ground-truth merge of its segments (each segment joins the instance it overlaps most: the ceiling of any merge),
the network's own segmentation (its method's embedding and clustering: the row the fold's record scores), and the
merge: agglomerative on the segments' adjacency graph (segments sharing at least ``--min-contact`` four-neighbour
pixel pairs), joining the adjacent pair whose size-weighted mean embeddings have the highest cosine while it
exceeds τ. The merge order does not depend on τ, so one pass per frame gives every τ of the grid. τ is chosen per
network on the training videos' frames (development data: their ground truth may choose a setting) and the test
frames are scored with it; the difference to lccp-frame gets a frame-bootstrap 95 % CI. A development dataset only:
this reads ground truth. The rule it answers: docs/experiments/2026-11-29-cluttered-segment-merging.md.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from common import save_rows

from selfseg.baselines.lccp_frame import LCCPFrameConfig, lccp_frame_labels
from selfseg.config import load_config
from selfseg.dataset import Dataset
from selfseg.eval.folds import fold_split, select_test_frames
from selfseg.eval.metrics import frame_metrics
from selfseg.method.meanshift import cluster_frame
from selfseg.registry import get_method_class

TAUS = (0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.95)
FRAME_STRIDE = 10  # the protocol's test frames


def adjacency(labels: np.ndarray, min_contact: int) -> set[tuple[int, int]]:
    """Pairs (a < b) of labels > 0 that share at least ``min_contact`` four-neighbour pixel pairs."""
    pairs = []
    for a, b in ((labels[:, :-1], labels[:, 1:]), (labels[:-1], labels[1:])):
        m = (a != b) & (a > 0) & (b > 0)
        pairs.append(np.stack([np.minimum(a[m], b[m]), np.maximum(a[m], b[m])], 1))
    uniq, counts = np.unique(np.concatenate(pairs), axis=0, return_counts=True)
    return {(int(a), int(b)) for (a, b), c in zip(uniq, counts) if c >= min_contact}


def merge_sequence(labels: np.ndarray, emb: np.ndarray, min_contact: int) -> list[tuple[int, int, float]]:
    """Greedy merges (kept label, absorbed label, cosine) of adjacent segments of ``labels`` (H×W, 0 = none) by the
    cosine of their size-weighted mean embeddings (``emb`` D×H×W), highest first, until no adjacent pair is left.
    A merged segment is adjacent to whatever either part was adjacent to."""
    ids = [int(i) for i in np.unique(labels) if i > 0]
    flat = labels.ravel()
    e = emb.reshape(emb.shape[0], -1)
    sums = {i: e[:, flat == i].sum(1).astype(np.float64) for i in ids}
    adj = adjacency(labels, min_contact)
    seq = []
    while adj:
        unit = {i: s / max(np.linalg.norm(s), 1e-12) for i, s in sums.items()}
        a, b = max(adj, key=lambda p: float(unit[p[0]] @ unit[p[1]]))
        seq.append((a, b, float(unit[a] @ unit[b])))
        sums[a] = sums[a] + sums.pop(b)
        adj = {(min(x, y), max(x, y)) for x, y in ((a if p == b else p, a if q == b else q) for p, q in adj) if x != y}
    return seq


def apply_merges(labels: np.ndarray, seq: list[tuple[int, int, float]], tau: float) -> np.ndarray:
    """``labels`` after the merges of ``seq`` up to the first whose cosine is ≤ ``tau``."""
    lut = np.arange(int(labels.max()) + 1)
    for a, b, c in seq:
        if c <= tau:
            break
        lut[lut == b] = a
    return lut[labels]


def gt_merge(labels: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Each segment of ``labels`` relabelled to the ground-truth instance it overlaps most (0 if none)."""
    out = np.zeros_like(gt)
    for i in np.unique(labels[labels > 0]):
        m = labels == i
        ids, counts = np.unique(gt[m & (gt > 0)], return_counts=True)
        out[m] = ids[np.argmax(counts)] if len(ids) else 0
    return out


def boot_ci(diff: np.ndarray, n: int = 2000) -> list[float]:
    rng = np.random.default_rng(0)
    boot = [diff[rng.integers(0, len(diff), len(diff))].mean() for _ in range(n)]
    return [round(float(q), 4) for q in np.percentile(boot, [2.5, 97.5])]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="development dataset folder")
    p.add_argument("--fold", type=int, default=0)
    p.add_argument("--work", required=True, help="folder for the cached lccp-frame labels")
    p.add_argument("--net", action="append", required=True, metavar="NAME=METHOD,CONFIG,WEIGHTS")
    p.add_argument("--min-contact", type=int, default=10)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", default="experiments/results/cluttered_segment_merging.json")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    ds = Dataset(args.data)
    nets = {}
    for spec in args.net:
        name, _, rest = spec.partition("=")
        method, config, weights = rest.split(",")
        cls = get_method_class(method)
        m = cls(load_config(cls.config_cls, config))
        m.load(weights)
        nets[name] = (m, {"method": method, "config": config, "weights": weights})
    train_ids, test_ids = fold_split(ds, args.fold)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    lccp_cfg = LCCPFrameConfig()
    rows = {"train": [], "test": []}  # per frame: {"lccp", "ceiling", "<net>": own, "<net>@tau": ...}
    t0 = time.perf_counter()
    for split, vids in (("test", test_ids), ("train", train_ids)):
        for vid in vids:
            video = ds.labeled(vid)
            for f in select_test_frames(video.frame_ids, FRAME_STRIDE, None):
                gt = video.inst(f).astype(np.int64)
                fg = gt > 0
                if not fg.any():
                    continue
                cache = work / f"lccp-{vid}-{f:06d}.npy"
                if cache.is_file():
                    lab = np.load(cache)
                else:
                    lab = lccp_frame_labels(video.depth_m(f), video.K(f), fg, lccp_cfg).astype(np.int64)
                    np.save(cache, lab)
                row = {"video_id": vid, "frame_id": f, "lccp": frame_metrics(lab, gt)["IoU"],
                       "ceiling": frame_metrics(gt_merge(lab, gt), gt)["IoU"]}
                rgb = video.rgb(f)
                for name, (m, _) in nets.items():
                    emb = m.embed(rgb, fg)
                    row[name] = frame_metrics(cluster_frame(emb, fg, m.config.cluster), gt)["IoU"]  # as segment_frame
                    seq = merge_sequence(lab, emb, args.min_contact)
                    for tau in TAUS:
                        row[f"{name}@{tau}"] = frame_metrics(apply_merges(lab, seq, tau), gt)["IoU"]
                rows[split].append(row)
            done = rows[split]
            print(f"{split} {vid}: {len(done)} frames, lccp {np.mean([r['lccp'] for r in done]):.4f}, ceiling "
                  f"{np.mean([r['ceiling'] for r in done]):.4f} ({time.perf_counter() - t0:.0f} s)", flush=True)
    out = []
    test = rows["test"]
    lccp = np.array([r["lccp"] for r in test])
    for name, (_, ident) in nets.items():
        train_means = {tau: float(np.mean([r[f"{name}@{tau}"] for r in rows["train"]])) for tau in TAUS}
        tau = max(TAUS, key=lambda t: (train_means[t], -t))
        merged = np.array([r[f"{name}@{tau}"] for r in test])
        res = {"data": args.data, "dataset_hash": ds.content_hash(), "fold": args.fold, "net": name, **ident,
               "min_contact": args.min_contact, "test_frames": len(test), "train_frames": len(rows["train"]),
               "train_iou_by_tau": {str(t): round(v, 4) for t, v in train_means.items()}, "tau": tau,
               "test_iou_by_tau": {str(t): round(float(np.mean([r[f"{name}@{t}"] for r in test])), 4) for t in TAUS},
               "iou_lccp": round(float(lccp.mean()), 4), "iou_ceiling": round(float(np.mean([r["ceiling"] for r in test])), 4),
               "iou_net": round(float(np.mean([r[name] for r in test])), 4), "iou_merged": round(float(merged.mean()), 4),
               "merged_minus_lccp": round(float((merged - lccp).mean()), 4),
               "merged_minus_lccp_ci95": boot_ci(merged - lccp), "wall_s": round(time.perf_counter() - t0, 1)}
        print({k: v for k, v in res.items() if k not in ("data", "weights", "config")}, flush=True)
        out.append(res)
    save_rows(args.json, out, lambda r: (r["dataset_hash"], r["fold"], r["net"], r["min_contact"]),
              "lccp-frame's segments merged by a learned embedding (experiments/bench_segment_merging.py)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
