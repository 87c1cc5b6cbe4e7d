"""Diagnostic, not a test: which touching objects does a method join in 2-D, and do they differ in colour?

    .venv/bin/python experiments/bench_touching_merges.py --data DIR --results RESULTS --method M [--method M2 ...]
                                                     [--json experiments/results/touching_merges.json]

For every scored frame of each method's run in RESULTS (``evaluate``'s predictions and per-frame records), two GT
instances touch when at least ``--min-contact-px`` pixels of one lie within 2 px of the other. A method joins the
pair when one predicted segment holds at least half of each object's pixels. Each pair's colour contrast is the
CIELAB distance ΔE (cv2's 8-bit Lab, L scaled to 0–100) between the two objects' mean colours in that frame; pairs
are binned by ΔE terciles (pooled over the methods' common frames) and by whether both instances are the same
object model. The join rate per bin says whether a method's joins follow appearance.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from common import joined, touching_pairs

from selfseg.dataset import Dataset, read_inst
from selfseg.eval.layout import FRAMES_JSONL, PREDICTION_PNG, PREDICTIONS_DIR
from selfseg.fileio import write_json


def delta_e(lab: np.ndarray, gt: np.ndarray, a: int, b: int) -> float:
    """CIELAB distance between the mean colours of instances ``a`` and ``b`` (``lab``: float H×W×3, L in 0–100)."""
    return float(np.linalg.norm(lab[gt == a].mean(0) - lab[gt == b].mean(0)))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True)
    p.add_argument("--results", required=True)
    p.add_argument("--method", action="append", required=True)
    p.add_argument("--min-contact-px", type=int, default=20)
    p.add_argument("--json", default="experiments/results/touching_merges.json")
    args = p.parse_args(argv)
    ds = Dataset(args.data)
    root = Path(args.results)
    frames = None  # (video_id, frame_id) scored by every method
    for m in args.method:
        paths = sorted(root.glob(FRAMES_JSONL.format(dataset=ds.name, name=m, fold="*")))
        if not paths:
            raise SystemExit(f"bench_touching_merges: no per-frame records of {m!r} in {root}")
        got = {(r["video_id"], r["frame_id"]) for pth in paths for r in map(json.loads, pth.read_text().splitlines())}
        frames = got if frames is None else frames & got
    pairs = []  # one row per touching pair per frame
    for vid, fid in sorted(frames):
        video = ds.labeled(vid)
        gt = video.inst(fid).astype(np.int64)
        lab = cv2.cvtColor(video.rgb(fid), cv2.COLOR_RGB2LAB).astype(np.float64)
        lab[..., 0] *= 100 / 255
        obj = video.instance_to_object()
        preds = {m: read_inst(root / PREDICTIONS_DIR.format(name=m, dataset=ds.name)
                              / PREDICTION_PNG.format(video_id=vid, frame_id=fid)).astype(np.int64) for m in args.method}
        for a, b in touching_pairs(gt, args.min_contact_px):
            pairs.append({"video_id": vid, "frame_id": fid, "a": a, "b": b, "same_model": obj[a] == obj[b],
                          "delta_e": delta_e(lab, gt, a, b), **{m: joined(preds[m], gt, a, b) for m in args.method}})
    if not pairs:
        raise SystemExit("bench_touching_merges: no touching pairs in the scored frames")
    edges = np.quantile([r["delta_e"] for r in pairs], [1 / 3, 2 / 3])
    bins = {f"ΔE < {edges[0]:.0f}": lambda r: r["delta_e"] < edges[0],
            f"ΔE {edges[0]:.0f}–{edges[1]:.0f}": lambda r: edges[0] <= r["delta_e"] < edges[1],
            f"ΔE ≥ {edges[1]:.0f}": lambda r: r["delta_e"] >= edges[1],
            "same model": lambda r: r["same_model"], "all": lambda r: True}
    table = []
    for name, sel in bins.items():
        rows = [r for r in pairs if sel(r)]
        table.append({"bin": name, "pairs": len(rows), **{m: float(np.mean([r[m] for r in rows])) if rows else None
                                                          for m in args.method}})
    print(f"{'bin':<14} {'pairs':>5} " + " ".join(f"{m:>18}" for m in args.method) + "   (share of pairs joined)")
    for t in table:
        print(f"{t['bin']:<14} {t['pairs']:>5} " + " ".join(
            f"{t[m]:>18.3f}" if t[m] is not None else f"{'—':>18}" for m in args.method))
    write_json(args.json, {"data": args.data, "dataset_hash": ds.content_hash(), "methods": args.method,
                           "frames": len(frames), "min_contact_px": args.min_contact_px, "bins": table, "pairs": pairs})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
