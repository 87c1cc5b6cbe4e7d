"""Diagnostic, not a test: how much of a method's IoU is lost to fragmentation (objects split in pieces)?

    .venv/bin/python experiments/bench_fragmentation.py --data DIR --results RESULTS --method M [--method M2 ...]
                                                   [--json experiments/results/fragmentation.json]

For every scored frame of every fold of each method's run in RESULTS (``evaluate``'s predictions and
per-frame records), each predicted segment on the GT foreground is relabelled with its majority GT
instance, so pieces of one object become one segment, and the frame is scored again. The rise in IoU
is what over-segmentation costs; what stays below 1.0 is under-segmentation (one segment over two
objects) and boundary errors. Also prints the mean ratio of predicted to GT segments per frame.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from selfseg.dataset import Dataset, read_inst
from selfseg.eval.layout import FRAMES_JSONL, PREDICTION_PNG, PREDICTIONS_DIR
from selfseg.eval.metrics import segment_metrics
from selfseg.fileio import write_json


def merge_fragments(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``pred`` (H×W ints, 0 = none) on the GT foreground with each segment relabelled by its majority
    GT instance of ``gt`` (0 = background)."""
    fg = gt > 0
    out = np.zeros_like(gt)
    for s in np.unique(pred[fg]):
        if s:
            sel = fg & (pred == s)
            out[sel] = np.bincount(gt[sel]).argmax()
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True)
    p.add_argument("--results", required=True)
    p.add_argument("--method", action="append", required=True)
    p.add_argument("--json", default="experiments/results/fragmentation.json")
    args = p.parse_args(argv)
    ds = Dataset(args.data)
    rows = []
    for method in args.method:
        scores = {"IoU": [], "IoU_fragments_merged": [], "pred_per_gt": []}
        frames = sorted(Path(args.results).glob(FRAMES_JSONL.format(dataset=ds.name, name=method, fold="*")))
        if not frames:
            raise SystemExit(f"bench_fragmentation: no per-frame records of {method!r} in {args.results}")
        for path in frames:
            for line in path.read_text().splitlines():
                r = json.loads(line)
                gt = ds.labeled(r["video_id"]).inst(r["frame_id"]).astype(np.int64)
                pred = read_inst(Path(args.results) / PREDICTIONS_DIR.format(name=method, dataset=ds.name)
                                 / PREDICTION_PNG.format(video_id=r["video_id"], frame_id=r["frame_id"])).astype(np.int64)
                scores["IoU"].append(segment_metrics(pred * (gt > 0), gt)["IoU"])
                scores["IoU_fragments_merged"].append(segment_metrics(merge_fragments(pred, gt), gt)["IoU"])
                scores["pred_per_gt"].append(r["n_pred"] / max(r["n_gt"], 1))
        rows.append({"method": method, "frames": len(scores["IoU"]), **{k: float(np.mean(v)) for k, v in scores.items()}})
    print(f"{'method':>16} {'frames':>6} {'IoU':>6} {'merged':>6} {'pred/gt':>7}")
    for r in rows:
        print(f"{r['method']:>16} {r['frames']:>6} {r['IoU']:.3f} {r['IoU_fragments_merged']:.3f} {r['pred_per_gt']:>7.2f}")
    write_json(args.json, {"data": args.data, "dataset_hash": ds.content_hash(), "rows": rows})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
