"""Diagnostic, not a test: ground-truth scores of the merges each Table I fold's matching step made on its
training videos (what ``evaluate3d`` reports for all videos as one collection, per fold instead).

    .venv/bin/python bench/bench_fold_merges.py --data runs/calibrated/data --config configs/ours-calibrated.yaml
        --results runs/calibrated/results --run ours [--run ours-v4 ...] [--json bench/results/fold_merges.json]

Reads the segments, reconstructions and GT point labels from ``evaluate3d``'s stage cache under RESULTS (run
it first; its stages are built from the same videos with the same settings as the folds' own; the number of
points and segments of every video is checked) and each fold's pseudo-labels and merge lists from
RESULTS/work/<run>/<dataset>/fold<k>/.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from selfseg.config import load_config
from selfseg.dataset import Dataset
from selfseg.eval.merges import merge_scores
from selfseg.eval.points import GT_MAX_DIST_M
from selfseg.eval.protocol import results_key
from selfseg.eval.table2 import labeled_scenes, merge_inputs
from selfseg.fileio import read_json, write_json
from selfseg.method.pipeline import LABELS_NPY, PSEUDO_CACHE_DIR, PSEUDO_STAGE, OursConfig
from selfseg.method.pruning import PruneConfig
from selfseg.method.pseudolabels import DIAGNOSTICS_JSON, SceneData, segment_clouds
from selfseg.stages import StageCache


def pseudo_stage(fold_dir: Path) -> Path:
    """A fold's pseudo-label stage folder, where :meth:`Ours.pseudo_labels` wrote it."""
    return StageCache(fold_dir / PSEUDO_CACHE_DIR).path(*PSEUDO_STAGE)


def gt_labeled(dataset: Dataset, config: OursConfig, results: str):
    """(segmentations, alignments, GT instance per point) of every video from ``evaluate3d``'s stages in RESULTS."""
    return labeled_scenes(dataset, config, Path(results), ("lccp+symseg",), None, GT_MAX_DIST_M, None, gt_labels=True)


def segment_clouds_of(scene, prune: PruneConfig) -> list[np.ndarray]:
    """Each segment's points of an ``evaluate3d`` scene, subsampled as pruning subsamples them."""
    n = scene.graph.n_segments
    return segment_clouds(SceneData(scene.video_id, scene.recon.points_w, scene.graph, np.zeros((n, 1))),
                          prune.max_points_per_node, prune.seed)


def fold_dirs(bench: str, results: str, dataset: Dataset, run: str, folds: str = "") -> list[Path] | None:
    """The fold work folders of ``run`` (only the comma-separated fold numbers ``folds``, if given); None after
    one line on stderr when there are none."""
    dirs = sorted(Path(results, "work", run, results_key(Path(results), dataset)).glob("fold[0-9]*"))
    if folds:
        dirs = [d for d in dirs if d.name[4:] in folds.split(",")]
    if not dirs:
        print(f"{bench}: {results}: no folds of run {run!r}", file=sys.stderr)
    return dirs or None


def fold_bench_parser(doc: str, json_default: str) -> argparse.ArgumentParser:
    """The arguments of the benches that read runs' fold folders: --data, --config, --results, --run (repeated),
    --folds and --json."""
    p = argparse.ArgumentParser(description=doc.split("\n")[0])
    p.add_argument("--data", required=True, help="a development dataset (reads its ground truth)")
    p.add_argument("--config", required=True, help="the config the runs and evaluate3d used")
    p.add_argument("--results", required=True, help="the runs' results folder (evaluate --out), with evaluate3d's")
    p.add_argument("--run", action="append", required=True, help="a run name (its folds' work folders)")
    p.add_argument("--folds", default="", help="fold numbers, comma-separated (default: every fold folder)")
    p.add_argument("--json", default=json_default)
    return p


def runs_folds(bench: str, args: argparse.Namespace, dataset: Dataset) -> list[tuple[str, Path]] | None:
    """(run, fold folder) for every ``--run`` and fold; None after one line on stderr when a run has none."""
    out = []
    for run in args.run:
        folds = fold_dirs(bench, args.results, dataset, run, args.folds)
        if folds is None:
            return None
        out += [(run, f) for f in folds]
    return out


def save(path: str, what: str, data: str, dataset: Dataset, config: str, rows: list[dict]) -> None:
    """Write the bench's rows with the dataset and config they were measured on."""
    write_json(path, {"what": what, "data": str(Path(data).resolve()), "dataset_hash": dataset.content_hash(),
                      "config": config, "rows": rows})
    print(f"wrote {path}")


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
    args = fold_bench_parser(__doc__, "bench/results/fold_merges.json").parse_args(argv)
    dataset = Dataset(args.data)
    config = load_config(OursConfig, args.config)
    seg, _, gt_inst = gt_labeled(dataset, config, args.results)
    folds = runs_folds("bench_fold_merges", args, dataset)
    if folds is None:
        return 2
    rows = [{"run": run, "fold": f.name, **fold_scores(f, seg, gt_inst, dataset)} for run, f in folds]
    print(f"{'run':<10} {'fold':<6} {'merges':>6} {'within P':>9} {'within R':>9} {'across P':>9} {'across R':>9}")
    f = lambda x: "–" if x is None else f"{x:.3f}"  # noqa: E731
    for r in rows:
        w, a = r["within"], r["across"]
        print(f"{r['run']:<10} {r['fold']:<6} {r['merges']:>6} {f(w['precision']):>9} {f(w['recall']):>9} "
              f"{f(a['precision']):>9} {f(a['recall']):>9}")
    save(args.json, "GT scores of each fold's merges (bench/bench_fold_merges.py)", args.data, dataset, args.config,
         rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
