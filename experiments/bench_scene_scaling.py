"""Diagnostic, not a test: how a learned method's IoU grows with the number of training scenes.

    .venv/bin/python experiments/bench_scene_scaling.py --data DIR --config configs/supervised-benchmark.yaml
        [--method supervised] [--sizes 2,4,8,16] [--test 4] [--set KEY=VALUE ...] [--work runs/scaling]
        [--json experiments/results/scene_scaling.json]

The last ``--test`` videos of DIR are the fixed test set (every 10th frame, ground-truth foreground, as
``evaluate``); for each size n the method is trained on the first n videos. Run it on a development set
(for example ``generate_scenes --preset benchmark --seed 100``), never on a benchmark test fold. Each size
writes ``WORK/<method>/n<n>.json`` when done, so a killed run resumes, and two processes with different
``--sizes`` can share one WORK folder (one per core); the table and the JSON cover every size on disk.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import time
from pathlib import Path

from selfseg.config import load_config
from selfseg.dataset import Dataset
from selfseg.eval.aggregate import SegmentationEvaluator
from selfseg.eval.folds import EvalOptions, select_test_frames
from selfseg.fileio import write_json
from selfseg.guard import ground_truth_forbidden
from selfseg.registry import get_method_class

FRAME_STRIDE = EvalOptions.frame_stride  # evaluate's default protocol


def run_size(ds: Dataset, method: str, config, n: int, test_ids: list[str], work: Path) -> dict:
    """Train ``method`` on the first ``n`` videos and score it on ``test_ids``; returns the record.
    A method that does not declare ``needs_ground_truth`` gets unlabeled videos and runs under the guard."""
    cls = get_method_class(method)
    model = cls(config, work / method / f"n{n}")
    model.stage_root = work / "_stages"
    open_video = ds.labeled if cls.needs_ground_truth else ds.video
    guard = contextlib.nullcontext if cls.needs_ground_truth else (lambda: ground_truth_forbidden(ds.root))
    train_ids = ds.video_ids[:n]
    t0 = time.perf_counter()
    with guard():
        model.fit([open_video(v) for v in train_ids])
    fit_s = time.perf_counter() - t0
    evaluator = SegmentationEvaluator()
    for vid in test_ids:
        labeled = ds.labeled(vid)
        frames = select_test_frames(labeled.frame_ids, FRAME_STRIDE, None)
        gts = {f: labeled.inst(f) for f in frames}
        with guard():
            preds = model.segment_video(open_video(vid), frames, {f: g > 0 for f, g in gts.items()})
        for f in frames:
            evaluator.process(vid, f, preds[f], gts[f])
    result = evaluator.evaluate()
    return {"n_train": n, "train_videos": train_ids, "test_videos": test_ids, "fit_s": round(fit_s, 1),
            "metrics": result["metrics"], "ci95": result["ci95"]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True)
    p.add_argument("--method", default="supervised")
    p.add_argument("--config", required=True)
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--sizes", default="2,4,8,16", help="training scene counts, comma-separated")
    p.add_argument("--test", type=int, default=4, help="the last TEST videos are the test set")
    p.add_argument("--work", default="runs/scaling")
    p.add_argument("--json", default="experiments/results/scene_scaling.json")
    args = p.parse_args(argv)
    ds = Dataset(args.data)
    sizes = [int(s) for s in args.sizes.split(",")]
    test_ids = ds.video_ids[-args.test:]
    if max(sizes) > len(ds.video_ids) - args.test:
        raise SystemExit(f"bench_scene_scaling: {ds.root} has {len(ds.video_ids)} videos: too few for "
                         f"{max(sizes)} training and {args.test} test videos")
    config = load_config(get_method_class(args.method).config_cls, args.config, args.overrides)
    work = Path(args.work)
    for n in sizes:
        out = work / args.method / f"n{n}.json"
        if out.is_file():
            continue
        rec = run_size(ds, args.method, config, n, test_ids, work)
        write_json(out, {**rec, "config": args.config, "overrides": args.overrides})
        print(f"n={n}: IoU {rec['metrics']['IoU']:.3f} ({rec['fit_s']:.0f} s training)", flush=True)
    rows = sorted((json.loads(f.read_text()) for f in (work / args.method).glob("n*.json")), key=lambda r: r["n_train"])
    print(f"{'scenes':>6} {'Prec':>5} {'Recall':>6} {'IoU':>5} {'IoU 95% CI':>11} {'fit s':>6}")
    for r in rows:
        m, ci = r["metrics"], r["ci95"]["IoU"]
        print(f"{r['n_train']:>6} {m['P']:.3f} {m['R']:>6.3f} {m['IoU']:.3f} {ci[0]:.3f}–{ci[1]:.3f} {r['fit_s']:>6.0f}")
    write_json(args.json, {"data": args.data, "dataset_hash": ds.content_hash(), "method": args.method,
                           "test_videos": test_ids, "frame_stride": FRAME_STRIDE, "rows": rows})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
