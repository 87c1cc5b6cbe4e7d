"""Table II (the ``evaluate3d`` command, :func:`selfseg.eval.cli.evaluate3d_main`): the 3-D segmentations
of the reconstructed scenes scored against GT points.

Rows (each a result record with ``task = "3d"``, named after the row):

- ``lccp``: the LCCP over-segmentation alone (``overseg.use_symseg=False``);
- ``lccp+symseg``: the pipeline's over-segmentation (LCCP + SymSeg, the ``overseg`` stage);
- ``ours-matching``: the per-point object pseudo-labels after graph matching and pruning (needs φ1,
  trained with the config's ``phi1_train`` schedule);
- ``gt-merging`` (a diagnostic, not in the paper): ``lccp+symseg`` with every segment-graph edge whose two
  segments share their majority GT instance merged (:func:`~selfseg.eval.merges.merge_same_instance`):
  the most a perfect matching and pruning step could merge on this over-segmentation.

The pipeline (:class:`selfseg.method.pipeline.Ours`) runs on **all** videos of the dataset as one
unlabeled collection, under :func:`~selfseg.guard.ground_truth_forbidden`: no labels are used, so
there are no folds and records carry ``fold = "all"``. Its stages live in the ``evaluate`` layout
(``OUT/work/ours/<dataset>/foldall``, per-video stages in ``OUT/work/_stages/``), so they are
shared with ``evaluate --method ours`` runs in the same ``OUT``. The stage cache holds one
over-segmentation per video (the configured one), so the ``lccp`` row re-runs LCCP in memory on the
cached reconstruction. What libraries print meanwhile (Open3D's registration warnings) goes to the run's
library log, ``foldall/library.log`` (:mod:`selfseg.library_log`), counted in one line at the end.

Scoring happens afterwards, outside the guard (:func:`selfseg.eval.points.evaluate_points`). With
estimated poses the reconstruction's world frame is the first posed camera's frame f0; it is mapped to
the dataset's world frame by T_gtworld_estworld = T_world_cam_gt(f0) · T_world_cam_est(f0)⁻¹. The
camera-position and -rotation error left after that alignment (pose drift) is recorded per video.
"""
from __future__ import annotations

import argparse
import concurrent.futures as cf
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from selfseg.config import ConfigError, config_hash, load_config
from selfseg.dataset import Dataset, DatasetError, LabeledVideo
from selfseg.eval.aggregate import fmt
from selfseg.eval.datastats import format_stats, overall_stats, scene_stats, view_stats
from selfseg.eval.merges import cosine_by_object, merge_same_instance, merge_scores, relabel, segment_instances
from selfseg.eval.points import GT_MAX_DIST_M, PointsEvaluator, gt_point_labels, gt_scene
from selfseg.eval.layout import FAILED_JSON, FRAMES_JSONL, LIBRARY_LOG, SCORES_JSON, STAGES_DIR, WORK_DIR
from selfseg.eval.protocol import EXIT_OVER_BUDGET, record_failure, write_result
from selfseg.eval.provenance import git_info, provenance, run_key
from selfseg.executor import executor_config, shared_executor
from selfseg.fileio import read_json, write_json
from selfseg.guard import ground_truth_forbidden
from selfseg.library_log import run_log, summary
from selfseg.method_api import BudgetExceededError
from selfseg.method.pipeline import ROWS_3D, Ours, OursConfig, Segmentations3D, lccp_only
from selfseg.method.recon_stage import ReconStage
from selfseg.poses import invert_T, transform_points

GT_MERGING = "gt-merging"  # lccp+symseg with the ground truth's merges (a ceiling for matching)
ROWS = (*ROWS_3D, GT_MERGING)
FOLD = "all"  # one collection of every video: no labels are used, so there are no folds
TABLE_KEYS = ("P", "R", "IoU", "overlap_P", "overlap_R", "overlap_F")
DRIFT_KEYS = ("drift_pos_mean_m", "drift_pos_max_m", "drift_rot_mean_deg")
STATS_JSON = "stats/{dataset}/{config_hash}.json"  # evaluate3d --stats: the data statistics of a dataset + config


def alignment(recon: ReconStage, labeled: LabeledVideo) -> tuple[np.ndarray, dict]:
    """(T_gtworld_reconworld 4×4, pose drift) of a reconstruction against the video's GT poses.

    Drift: position (m) and rotation (deg) error of every posed camera after the alignment at f0, the
    first frame with an estimated pose; zero by construction at f0 and everywhere with GT poses.
    """
    if not recon.T_world_cam:
        raise DatasetError(f"{recon.dir}: the reconstruction has no camera poses")
    f0 = min(recon.T_world_cam)
    if recon.report.get("world_frame") == "dataset":
        T = np.eye(4)
    else:
        T = labeled.T_world_cam(f0) @ invert_T(recon.T_world_cam[f0])
    pos, rot = [], []
    for f, T_est in sorted(recon.T_world_cam.items()):
        T_gt, T_al = labeled.T_world_cam(f), T @ T_est
        pos.append(np.linalg.norm(T_al[:3, 3] - T_gt[:3, 3]))
        cos = (np.trace(T_gt[:3, :3].T @ T_al[:3, :3]) - 1) / 2
        rot.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return T, {"align_frame": int(f0), "drift_pos_mean_m": float(np.mean(pos)), "drift_pos_max_m": float(np.max(pos)),
               "drift_rot_mean_deg": float(np.mean(rot))}


def table2_pipeline(dataset: Dataset, config: OursConfig, out: Path) -> Ours:
    """The pipeline as ``evaluate3d`` runs it on ``dataset``: workdir ``OUT/work/ours/<dataset>/foldall``, per-video
    stages under ``OUT/work/_stages`` (where :meth:`Ours.stage_cache` and :meth:`Ours.pseudo_dir` find its files)."""
    method = Ours(config, Path(out) / WORK_DIR.format(name=Ours.name, dataset=dataset.name, fold=FOLD))
    method.stage_root = Path(out) / STAGES_DIR
    return method


def segment_scenes(dataset: Dataset, config: OursConfig, out: Path, rows=ROWS_3D, executor: cf.Executor | None = None
                   ) -> Segmentations3D:
    """The pipeline's 3-D segmentations of every video of ``dataset`` (:meth:`Ours.segment_3d`), asked for
    with the dataset's ground truth guarded; its stages live in ``out``'s evaluate layout (shared with
    ``evaluate --method ours`` runs there). ``executor`` runs the per-video stages, matching and registration
    tasks (e.g. Ray); None: the stages in this process, matching and registrations in a local process pool."""
    method = table2_pipeline(dataset, config, out)
    method.executor = executor
    with ground_truth_forbidden(dataset.root):
        return method.segment_3d([dataset.video(v) for v in dataset.video_ids], rows)


def merge_inputs(dataset: Dataset, scenes, point_objects: dict[str, np.ndarray], gt_inst: dict[str, np.ndarray]
                 ) -> tuple[dict, dict, dict, dict]:
    """What :func:`selfseg.eval.merges.merge_scores` takes, per video of ``scenes`` (:class:`Segmentation3D`):
    the majority GT instance of each segment, the instance → obj_id map, each segment's object in
    ``point_objects`` (the pseudo-label of every reconstructed point, −1 = none) and the segment graph's edges."""
    seg_inst, inst_obj, seg_object, edges = {}, {}, {}, {}
    for s in scenes:
        n = len(s.graph.sizes)
        labels = np.asarray(s.graph.labels)
        seg_inst[s.video_id] = segment_instances(labels, gt_inst[s.video_id], n)
        inst_obj[s.video_id] = dataset.labeled(s.video_id).instance_to_object()
        obj = np.full(n, -1, np.int64)
        obj[labels[labels >= 0]] = point_objects[s.video_id][labels >= 0]
        seg_object[s.video_id] = obj
        edges[s.video_id] = np.asarray(s.graph.edges)
    return seg_inst, inst_obj, seg_object, edges


def matching_record(dataset: Dataset, seg: Segmentations3D, gt_inst: dict[str, np.ndarray]) -> dict:
    """The matching step's diagnostics with its ground-truth scores: merge precision/recall and the φ1 cosine
    of same- vs different-object segment pairs across scenes (:mod:`selfseg.eval.merges`). ``gt_inst``: GT
    instance per reconstructed point, per video."""
    seg_inst, inst_obj, seg_object, edges = merge_inputs(
        dataset, seg.scenes, {s.video_id: s.labels["ours-matching"] for s in seg.scenes}, gt_inst)
    feats = {s.video_id: s.features for s in seg.scenes}
    return {**seg.diagnostics, "gt": {**merge_scores(seg.diagnostics, seg_inst, inst_obj, seg_object, edges),
                                      "cosine": cosine_by_object(feats, seg_inst, inst_obj)}}


def format_matching(m: dict) -> str:
    """Lines summing up the matching record of the ``ours-matching`` row."""
    f = lambda x: "–" if x is None else f"{x:.3f}"  # noqa: E731
    mt, pr, gt = m["matching"], m["pruning"], m["gt"]
    w, a, c = gt["within"], gt["across"], gt["cosine"]
    cos = lambda d: f"median {f(d['median'])} (q25 {f(d['q25'])}, q75 {f(d['q75'])}, max {f(d['max'])}, n {d['n']})"  # noqa: E731
    return "\n".join([
        f"matching: {m['totals']['segments']} segments, {m['totals']['components']} components; component pairs "
        f"{mt.get('component_pairs', '–')}, pre-filtered {mt.get('prefiltered', '–')}, solved {mt.get('solved', '–')}, "
        f"non-empty {mt.get('nonempty', '–')}; merges {m['totals']['merges']} ({m['totals']['merged_segments']} segments)",
        f"pruning: matches {pr['matches_by_outcome']}; node pairs {pr['node_pairs_by_reason']}",
        f"merges within scenes: P {f(w['precision'])} ({w['correct']}/{w['merges']}), R {f(w['recall'])} "
        f"({w['merged']}/{w['same_instance_adjacent']} adjacent same-instance pairs)",
        f"matched pairs across scenes: P {f(a['precision'])} ({a['correct']}/{a['pairs']}), R {f(a['recall'])} "
        f"({a['matched_segments']}/{a['reappearing_segments']} segments of reappearing objects)",
        f"φ1 cosine across scenes: same object {cos(c['same_object'])}; different {cos(c['different_object'])}"])


def _row_seconds(row: str, seconds: dict[str, float]) -> float:
    steps = {"lccp": ("recon_overseg_s", "lccp_s"), "lccp+symseg": ("recon_overseg_s",),
             "ours-matching": ("recon_overseg_s", "phi1_s", "pseudo_s"), GT_MERGING: ("recon_overseg_s",)}[row]
    return sum(seconds.get(k, 0.0) for k in steps)


def labeled_scenes(dataset: Dataset, config: OursConfig, out: Path, rows, models: dict[str, dict] | None,
                   max_dist_m: float, executor: cf.Executor | None, gt_labels: bool
                   ) -> tuple[Segmentations3D, dict[str, tuple[np.ndarray, dict]], dict[str, np.ndarray]]:
    """The pipeline's segmentations of ``rows`` (``gt-merging`` built from ``lccp+symseg``), each video's
    alignment to the dataset's world frame (:func:`alignment`) and, with ``gt_labels``, the GT instance of
    every reconstructed point ({} otherwise)."""
    seg = segment_scenes(dataset, config, out,
                         tuple(r for r in rows if r in ROWS_3D) or ("lccp+symseg",), executor)
    aligned = {s.video_id: alignment(s.recon, dataset.labeled(s.video_id)) for s in seg.scenes}
    gt_inst = {}
    if gt_labels or GT_MERGING in rows:
        gt_inst = {s.video_id: gt_point_labels(transform_points(s.recon.points_w, aligned[s.video_id][0]), dataset,
                                               s.video_id, max_dist_m, None if models is None else models[s.video_id])
                   for s in seg.scenes}
    if GT_MERGING in rows:
        for s in seg.scenes:
            inst = segment_instances(s.graph.labels, gt_inst[s.video_id], s.graph.n_segments)
            s.labels[GT_MERGING] = relabel(s.graph.labels, merge_same_instance(s.graph.edges, inst))
    return seg, aligned, gt_inst


def run_stats(dataset: Dataset, config: OursConfig, out: Path, models: dict[str, dict] | None = None,
              max_dist_m: float = GT_MAX_DIST_M, executor: cf.Executor | None = None) -> dict:
    """The data statistics of :mod:`selfseg.eval.datastats` for every video (rows ``lccp``, ``lccp+symseg``
    and ``gt-merging``), written to ``out``/:data:`STATS_JSON`; returns the record."""
    git_info()  # the code as loaded, before any work
    rows = ("lccp", "lccp+symseg", GT_MERGING)
    seg, aligned, gt_inst = labeled_scenes(dataset, config, out, rows, models, max_dist_m, executor, gt_labels=True)
    scenes = {}
    for s in tqdm(seg.scenes, desc="data statistics", unit="video"):
        T = aligned[s.video_id][0]
        gt = gt_scene(dataset, s.video_id, None if models is None else models[s.video_id])
        views = view_stats(dataset, s.video_id)
        scenes[s.video_id] = scene_stats(transform_points(s.recon.points_w, T), s.labels, gt_inst[s.video_id], gt,
                                         views)
        scenes[s.video_id]["pose_drift"] = aligned[s.video_id][1]
    record = {**provenance(Ours.name, "data-stats", config, dataset, "stats"), "scenes": scenes,
              "overall": overall_stats(scenes), "options": {"max_dist_m": max_dist_m}}
    write_json(Path(out) / STATS_JSON.format(dataset=dataset.name, config_hash=record["config_hash"]), record)
    return record


def earlier_records(out: Path, dataset: Dataset, rows: tuple[str, ...], config: OursConfig, max_dist_m: float
                    ) -> dict[str, dict | None]:
    """{row: the record an identical earlier run filed for it in ``out`` (the same row config, dataset content, commit
    and ``max_dist_m``, with its per-video records in place), or its failure record (the same config, dataset and
    commit: the same run would pass the same budget), or None}. Reused as ``evaluate`` reuses a finished fold
    (:mod:`selfseg.eval.resume`), so a resumed run does not score a finished row again."""
    commit = git_info()["commit"]
    if commit is None:
        return dict.fromkeys(rows)
    content = dataset.content_hash()  # one scan of the dataset for every row
    found = {}
    for row in rows:
        where = {"dataset": dataset.name, "name": row, "fold": FOLD}
        want = {"method": Ours.name, "config_hash": config_hash(lccp_only(config) if row == "lccp" else config),
                "dataset": content, "commit": commit}
        found[row] = None
        scores, failed = Path(out) / SCORES_JSON.format(**where), Path(out) / FAILED_JSON.format(**where)
        if scores.is_file() and (Path(out) / FRAMES_JSONL.format(**where)).is_file():
            rec = read_json(scores)
            if run_key(rec) == want and rec.get("options", {}).get("max_dist_m") == max_dist_m:
                found[row] = rec
        if found[row] is None and failed.is_file() and run_key(rec := read_json(failed)) == want:
            found[row] = rec
    return found


def run_table2(dataset: Dataset, config: OursConfig, out: Path, rows=ROWS, models: dict[str, dict] | None = None,
               max_dist_m: float = GT_MAX_DIST_M, progress: bool = True,
               executor: cf.Executor | None = None) -> list[dict]:
    """Segment every video, score each row against the GT points and write its result record; a row that an
    identical earlier run finished (or failed under its budget) keeps that record (:func:`earlier_records`).

    ``models`` ({video_id: {obj_id: mesh in metres, model frame}}) overrides the dataset's model files
    (analytic test scenes have none). Returns the records, in the order of ``rows``. If the matching passes its
    budget (:class:`~selfseg.method_api.BudgetExceededError`), the ``ours-matching`` row gets a failure record
    instead (returned in its place, with its ``failure``) and the other rows are scored as usual.
    """
    git_info()  # the code as loaded, before any work
    bad = [r for r in rows if r not in ROWS]
    if bad or not rows:
        raise ConfigError(f"--rows: unknown row(s) {bad or rows!r}; choose from {', '.join(ROWS)}")
    out = Path(out)
    earlier = earlier_records(out, dataset, rows, config, max_dist_m)
    if progress and any(earlier.values()):
        print(f"evaluate3d: {', '.join(r for r in rows if earlier[r])}: the records of an identical earlier run "
              "(same config, data and commit) are kept", file=sys.stderr)
    todo = tuple(r for r in rows if earlier[r] is None)
    new = {r["name"]: r for r in _score_rows(dataset, config, out, todo, models, max_dist_m, progress, executor)} \
        if todo else {}
    return [earlier[r] or new[r] for r in rows]


def _score_rows(dataset: Dataset, config: OursConfig, out: Path, rows: tuple[str, ...], models: dict[str, dict] | None,
                max_dist_m: float, progress: bool, executor: cf.Executor | None) -> list[dict]:
    """:func:`run_table2`'s work for the rows it does not keep: segment, score, write each row's record."""
    failure = {}
    try:
        seg, aligned, gt_inst = labeled_scenes(dataset, config, out, rows, models, max_dist_m, executor,
                                               gt_labels="ours-matching" in rows or GT_MERGING in rows)
    except BudgetExceededError as e:
        if "ours-matching" not in rows:
            raise
        where = {"dataset": dataset.name, "name": "ours-matching", "fold": FOLD}
        failure = read_json(record_failure(out, where, {
            **provenance(Ours.name, "ours-matching", config, dataset, "3d"), "fold": FOLD, "n_folds": 1,
            "train_videos": list(dataset.video_ids), "test_videos": list(dataset.video_ids)}, e))
        rest = tuple(r for r in rows if r != "ours-matching")
        if not rest:
            return [failure]
        seg, aligned, gt_inst = labeled_scenes(dataset, config, out, rest, models, max_dist_m, executor,
                                               gt_labels=GT_MERGING in rest)
    scenes, seconds = seg.scenes, seg.seconds
    n_frames = sum(len(s.recon.frame_ids) for s in scenes)
    records = []
    for row in rows:
        if failure and row == "ours-matching":
            records.append(failure)
            continue
        ev = PointsEvaluator(dataset, max_dist_m)
        t0 = time.perf_counter()
        for s in tqdm(scenes, desc=f"score {row}", unit="video", disable=not progress):
            T, drift = aligned[s.video_id]
            rec = ev.process(s.video_id, s.recon.points_w, s.labels[row] + 1, T,  # labels: −1 none → 0 unlabeled
                             None if models is None else models[s.video_id])
            rec.update(drift, n_points=len(s.recon.points_w),
                       scored_fraction=rec["n_points_scored"] / max(len(s.recon.points_w), 1))
        score_s = time.perf_counter() - t0
        fit_s = _row_seconds(row, seconds)
        record = {
            **provenance(Ours.name, row, lccp_only(config) if row == "lccp" else config, dataset, "3d"),
            "fold": FOLD,
            "n_folds": 1,
            "train_videos": list(dataset.video_ids),
            "test_videos": list(dataset.video_ids),
            "options": {"max_dist_m": max_dist_m, "world_frame": scenes[0].recon.report.get("world_frame")},
            **ev.evaluate(),
            "pose_drift": {k: float(np.mean([aligned[s.video_id][1][k] for s in scenes])) for k in DRIFT_KEYS},
            "scored_fraction_min": float(min(r["scored_fraction"] for r in ev.records)),  # low: misaligned video
            "timings": {"fit_s": round(fit_s, 4), "ms_per_frame": round(1000 * fit_s / max(n_frames, 1), 4),
                        "score_s": round(score_s, 4), "steps_s": {k: round(v, 4) for k, v in seconds.items()}},
        }
        if row == "ours-matching":
            record["matching"] = matching_record(dataset, seg, gt_inst)
        write_result(out, record, ev.records)
        records.append(record)
    return records


def format_table(records: list[dict]) -> str:
    """One line per row: metrics over videos, mean camera drift, the least share of a video's points that lie
    on a GT object (low = misaligned or drifted video), pipeline seconds."""
    head = ["row", "videos", *TABLE_KEYS, "drift mm", "min scored %", "fit s"]
    rows = [[r["name"], str(r["metrics"]["n_frames"]), *(fmt(r["metrics"][k]) for k in TABLE_KEYS),
             f"{1000 * r['pose_drift']['drift_pos_mean_m']:.1f}", f"{100 * r['scored_fraction_min']:.0f}",
             f"{r['timings']['fit_s']:.1f}"] for r in records]
    widths = [max(len(x) for x in col) for col in zip(head, *rows)]
    line = lambda cells: "  ".join(c.rjust(w) for c, w in zip(cells, widths))  # noqa: E731
    return "\n".join([f"Table II (3-D points) on {records[0]['dataset']['name']}", line(head), *map(line, rows)])


def run(args: argparse.Namespace) -> int:
    """The ``evaluate3d`` command on parsed arguments (:func:`selfseg.eval.cli.evaluate3d_parser`): Table II, or
    with ``--stats`` the data statistics, computed and printed."""
    dataset = Dataset(args.data)
    config = load_config(OursConfig, args.config, args.overrides)
    rows = tuple(r.strip() for r in args.rows.split(",") if r.strip())
    where = executor_config(args, args.config)
    compute = (lambda ex: run_stats(dataset, config, args.out, executor=ex)) if args.stats else \
        (lambda ex: run_table2(dataset, config, args.out, rows, progress=not args.quiet, executor=ex))
    with run_log(Path(args.out) / LIBRARY_LOG.format(name=Ours.name, dataset=dataset.name, fold=FOLD)) as log:
        if not where.distributed:
            result = compute(None)
        else:
            with shared_executor(where, args.out) as executor:
                result = compute(executor)
    logged = summary(log)
    if logged:
        print(f"evaluate3d: {logged}", file=sys.stderr)
    if args.stats:
        print(format_stats({**result, "dataset": dataset.name}))
        print("statistics: " + str(args.out / STATS_JSON.format(dataset=dataset.name, config_hash=result["config_hash"])))
        return 0
    records = [r for r in result if "failure" not in r]
    if records:
        print(format_table(records))
    for r in records:
        if "matching" in r:
            print(format_matching(r["matching"]))
    print("results: " + ", ".join(str(args.out / SCORES_JSON.format(dataset=dataset.name, name=r["name"], fold=FOLD))
                                  for r in records))
    failed = [r for r in result if "failure" in r]
    for r in failed:
        path = args.out / FAILED_JSON.format(dataset=dataset.name, name=r["name"], fold=FOLD)
        print(f"evaluate3d: row {r['name']} failed under its budget: {r['failure']['message']} (recorded in {path})",
              file=sys.stderr)
    return EXIT_OVER_BUDGET if failed else 0
