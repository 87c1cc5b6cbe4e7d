"""Aggregation of per-frame metrics: per video, per dataset, over folds, bootstrap CIs over videos.

The dataset score of a metric is the mean over scored frames (frames with at least one
ground-truth object; the paper's "dataset score averages over frames"). The 95% confidence
interval resamples *videos* with replacement (frames of a video are not independent) and
recomputes that frame-weighted mean, with a fixed seed so results are reproducible.
"""
from __future__ import annotations

import math
from collections import defaultdict

import numpy as np

from selfseg.eval.metrics import METRIC_KEYS, frame_metrics

N_BOOTSTRAP = 2000
BOOTSTRAP_SEED = 0


def mean_metrics(frames: list[dict], keys=METRIC_KEYS) -> dict:
    """Mean of each metric over the frames that have ground-truth objects; adds ``n_frames``."""
    scored = [f for f in frames if f["n_gt"] > 0]
    out = {k: (float(np.mean([f[k] for f in scored])) if scored else float("nan")) for k in keys}
    out["n_frames"] = len(scored)
    return out


def per_video(frames: list[dict], keys=METRIC_KEYS) -> dict[str, dict]:
    """{video_id: mean metrics of its frames (+ n_frames)}, sorted by video id."""
    groups: dict[str, list[dict]] = defaultdict(list)
    for f in frames:
        groups[f["video_id"]].append(f)
    return {vid: mean_metrics(groups[vid], keys) for vid in sorted(groups)}


def bootstrap_ci(videos: dict[str, dict], keys=METRIC_KEYS, n_boot: int = N_BOOTSTRAP,
                 seed: int = BOOTSTRAP_SEED, level: float = 0.95) -> dict[str, list[float]]:
    """Percentile CI of the frame-weighted mean, resampling videos; ``videos`` as from :func:`per_video`."""
    vids = [v for v in sorted(videos) if videos[v]["n_frames"] > 0]
    if not vids:
        return {k: [float("nan"), float("nan")] for k in keys}
    w = np.array([videos[v]["n_frames"] for v in vids], dtype=np.float64)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(vids), size=(n_boot, len(vids)))
    counts = np.stack([np.bincount(row, minlength=len(vids)) for row in idx]) * w  # n_boot × n_videos
    out = {}
    for k in keys:
        vals = np.array([videos[v][k] for v in vids], dtype=np.float64)
        stats = counts @ vals / counts.sum(1)
        lo, hi = np.quantile(stats, [(1 - level) / 2, (1 + level) / 2])
        out[k] = [float(lo), float(hi)]
    return out


def summarize_folds(fold_results: list[dict], keys=METRIC_KEYS, n_boot: int = N_BOOTSTRAP,
                    seed: int = BOOTSTRAP_SEED) -> dict:
    """Combine result records of several folds of one method on one dataset.

    Returns {mean, std (sample std over folds; NaN with one fold), ci95 (bootstrap over the
    videos of all folds), folds [k], n_frames, ms_per_frame (mean over folds)}.
    """
    per_fold = np.array([[r["metrics"][k] for k in keys] for r in fold_results], dtype=np.float64)
    videos = {v: m for r in fold_results for v, m in r["per_video"].items()}
    n = len(fold_results)
    return {
        "mean": dict(zip(keys, per_fold.mean(0).tolist())),
        "std": dict(zip(keys, (per_fold.std(0, ddof=1) if n > 1 else np.full(len(keys), np.nan)).tolist())),
        "ci95": bootstrap_ci(videos, keys, n_boot, seed),
        "folds": sorted(r["fold"] for r in fold_results),
        "n_frames": int(sum(r["metrics"]["n_frames"] for r in fold_results)),
        "ms_per_frame": float(np.mean([r["timings"]["ms_per_frame"] for r in fold_results])),
    }


def fmt(x: float, digits: int = 3) -> str:
    """'.912' style number as in the paper's tables; '—' for NaN."""
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "—"
    s = f"{x:.{digits}f}"
    return s[1:] if s.startswith("0.") else s


class SegmentationEvaluator:
    """detectron2-style evaluator: ``reset()``, ``process(...)`` per frame, ``evaluate()`` at the end."""

    def __init__(self, n_boot: int = N_BOOTSTRAP, seed: int = BOOTSTRAP_SEED):
        self.n_boot = n_boot
        self.seed = seed
        self.frames: list[dict] = []

    def reset(self) -> None:
        self.frames = []

    def process(self, video_id: str, frame_id: int, pred: np.ndarray, gt: np.ndarray) -> dict:
        """Score one frame (H×W instance maps) and keep its record; returns the record."""
        rec = {"video_id": video_id, "frame_id": int(frame_id), **frame_metrics(pred, gt)}
        self.frames.append(rec)
        return rec

    def evaluate(self) -> dict:
        """{metrics (mean over frames + n_frames), per_video, ci95}."""
        videos = per_video(self.frames)
        return {"metrics": mean_metrics(self.frames), "per_video": videos,
                "ci95": bootstrap_ci(videos, n_boot=self.n_boot, seed=self.seed)}
