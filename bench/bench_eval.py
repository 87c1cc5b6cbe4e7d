"""Benchmark of the evaluator: time to score one frame, and to evaluate a whole dataset.

    .venv/bin/python bench/bench_eval.py [--data DIR] [--method fg-components] [--out bench/results/eval.json]

Frame timings use synthetic instance maps with 12 objects (640×480 and 320×240) and a
prediction that splits, merges and shifts them. The dataset timing runs the whole protocol
(3 folds, every 10th frame; every frame for the analytic dataset, which has only 6) with the
given method; without ``--data`` it builds the ray-cast analytic test dataset in a temp folder.
"""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from common import bench_parser, write_result

from selfseg.analytic import make_dataset, two_box_scenes
from selfseg.dataset import Dataset
from selfseg.eval.folds import EvalOptions
from selfseg.eval.metrics import frame_metrics
from selfseg.eval.protocol import run_fold
from selfseg.registry import get_method_class


def synthetic_frame(h: int, w: int, n_objects: int = 12, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(pred, gt): discs of random size; the prediction merges two, splits one and shifts all by 2 px."""
    rng = np.random.default_rng(seed)
    gt = np.zeros((h, w), np.uint16)
    yy, xx = np.mgrid[:h, :w]
    for k in range(1, n_objects + 1):
        cy, cx, r = rng.uniform(0.1 * h, 0.9 * h), rng.uniform(0.1 * w, 0.9 * w), rng.uniform(0.04, 0.1) * h
        gt[(yy - cy) ** 2 + (xx - cx) ** 2 < r * r] = k
    pred = np.roll(gt, 2, axis=1).astype(np.uint16)
    pred[pred == 2] = 1
    pred[(pred == 3) & (xx % 2 == 0)] = 40
    return pred, gt


def time_frame(h: int, w: int, repeats: int) -> float:
    pred, gt = synthetic_frame(h, w)
    frame_metrics(pred, gt)  # warm up imports
    t0 = time.perf_counter()
    for _ in range(repeats):
        frame_metrics(pred, gt)
    return 1000 * (time.perf_counter() - t0) / repeats


def main(argv: list[str] | None = None) -> int:
    p = bench_parser(__doc__, "eval.json")
    p.add_argument("--data", type=Path, help="dataset folder (default: build the analytic test dataset)")
    p.add_argument("--method", default="fg-components")
    p.add_argument("--repeats", type=int, default=50)
    args = p.parse_args(argv)

    report = {"frame_ms": {f"{w}x{h}": round(time_frame(h, w, args.repeats), 3) for h, w in ((480, 640), (240, 320))}}
    with tempfile.TemporaryDirectory() as tmp:
        if args.data is None:
            data, stride = make_dataset(Path(tmp) / "analytic", two_box_scenes()), 1
        else:
            data, stride = args.data, 10
        dataset = Dataset(data)
        cls = get_method_class(args.method)
        options = EvalOptions(frame_stride=stride)
        t0 = time.perf_counter()
        records = [run_fold(cls, cls.config_cls(), dataset, k, Path(tmp) / "results", options) for k in range(3)]
        total = time.perf_counter() - t0
    n = sum(r["metrics"]["n_frames"] for r in records)
    report["dataset"] = {
        "name": dataset.name, "method": args.method, "frame_stride": stride, "frames_scored": n,
        "total_s": round(total, 3),
        "score_ms_per_frame": round(float(np.mean([r["timings"]["score_ms_per_frame"] for r in records])), 3),
        "segment_ms_per_frame": round(float(np.mean([r["timings"]["ms_per_frame"] for r in records])), 3),
        "resolution": [dataset.width, dataset.height],
    }
    print(report)
    write_result(args.out, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
