"""Diagnostic, not a test: ground-truth scores of the merges each Table I fold's matching step made on its
training videos (what ``evaluate3d`` reports for all videos as one collection, per fold instead).

    .venv/bin/python experiments/bench_fold_merges.py --data runs/calibrated/data --config configs/ours-calibrated.yaml
        --results runs/calibrated/results --run ours [--run ours-v4 ...] [--json experiments/results/fold_merges.json]

Reads the segments, reconstructions and GT point labels from ``evaluate3d``'s stage cache under RESULTS (run
it first; its stages are built from the same videos with the same settings as the folds' own; the number of
points and segments of every video is checked) and each fold's pseudo-labels and merge lists from
RESULTS/work/<run>/<dataset>/fold<k>/.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from common import fold_bench_inputs, fold_bench_parser, pseudo_stage, save

from selfseg.dataset import Dataset
from selfseg.eval.merges import merge_scores
from selfseg.eval.table2 import merge_inputs
from selfseg.fileio import read_json
from selfseg.method.pipeline import LABELS_NPY
from selfseg.method.pseudolabels import DIAGNOSTICS_JSON


def fold_scores(fold_dir: Path, seg, gt_inst, dataset: Dataset) -> dict:
    """merge_scores of one fold's pseudo stage (``fold_dir``/pseudo/all/scenes) over its training videos."""
    stage = pseudo_stage(fold_dir)
    diag = read_json(stage / DIAGNOSTICS_JSON)
    scenes = {s.video_id: s for s in seg.scenes if s.video_id in diag["scenes"]}
    point_obj = {vid: np.load(stage / LABELS_NPY.format(video_id=vid)) for vid in scenes}
    for vid, s in scenes.items():
        if point_obj[vid].shape != np.shape(s.graph.labels) or diag["scenes"][vid]["segments"] != s.graph.n_segments:
            raise SystemExit(f"bench_fold_merges: {stage}: video {vid}'s reconstruction or segments differ from "
                             "evaluate3d's; the scores would not be comparable")
    seg_inst, inst_obj, seg_object, edges = merge_inputs(dataset, scenes.values(), point_obj, gt_inst)
    return {"videos": sorted(scenes), "merges": diag["totals"]["merges"],
            "outcomes": diag["pruning"]["matches_by_outcome"],
            **merge_scores(diag, seg_inst, inst_obj, seg_object, edges)}


def main(argv: list[str] | None = None) -> int:
    args = fold_bench_parser(__doc__, "experiments/results/fold_merges.json").parse_args(argv)
    inputs = fold_bench_inputs("bench_fold_merges", args)
    if inputs is None:
        return 2
    dataset, config, seg, _, gt_inst, folds = inputs
    rows = [{"run": run, "fold": f.name, **fold_scores(f, seg, gt_inst, dataset)} for run, f in folds]
    print(f"{'run':<10} {'fold':<6} {'merges':>6} {'within P':>9} {'within R':>9} {'across P':>9} {'across R':>9}")
    f = lambda x: "–" if x is None else f"{x:.3f}"  # noqa: E731
    for r in rows:
        w, a = r["within"], r["across"]
        print(f"{r['run']:<10} {r['fold']:<6} {r['merges']:>6} {f(w['precision']):>9} {f(w['recall']):>9} "
              f"{f(a['precision']):>9} {f(a['recall']):>9}")
    save(args.json, "GT scores of each fold's merges (experiments/bench_fold_merges.py)", args.data, dataset,
         args.config, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
