"""The paper's evaluation protocol: 3-fold cross-validation over videos, every 10th test frame.

For each fold the method is built fresh, ``fit`` on the fold's training videos and asked to
segment the test frames of its held-out videos, given the ground-truth foreground masks.
Every method runs in its own process, in a sandbox (:mod:`selfseg.eval.sandbox`) that holds the fold's
inputs only (:mod:`selfseg.eval.mounts`): the videos of a copy of the dataset without ground truth, read as
unlabeled :class:`~selfseg.dataset.Video` objects. Only registered methods whose registry entry gives them
labels (and a user's method run with ``--method-needs-ground-truth``) get the fold's *training* videos with
their labels, as :class:`~selfseg.dataset.LabeledVideo` objects; the test videos' labels only the oracle.
The method writes its predictions into a folder of its own; the evaluator reads them once the method's
process has exited, checks them, scores them (:mod:`selfseg.eval.scoring`) and files them under ``OUT`` in the
layout of :mod:`selfseg.eval.layout`: a result record per fold (:func:`~selfseg.eval.provenance.provenance`'s
fields, then the fold's videos, options, metrics and timings: :func:`run_fold`) and a line of metrics per test
frame (:func:`write_result`).

The folds and test frames are :mod:`selfseg.eval.folds`'; a run name holds one run, and a fold an identical
earlier run finished is reused (:mod:`selfseg.eval.resume`).
"""
from __future__ import annotations

import dataclasses
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from selfseg.config import ConfigError, from_dict
from selfseg.dataset import Dataset, DatasetError
from selfseg.eval.folds import EvalOptions, fold_split, select_test_frames
from selfseg.eval.layout import (FAILED_JSON, FOLD_LOCK, FRAMES_JSONL, LIBRARY_LOG, METHOD_OUTPUT_DIR, N_FOLDS,
                                 PREDICTION_PNG, PREDICTIONS_DIR, REJECTED_JSON, SCORES_JSON, results_key)
from selfseg.eval.mounts import fold_mounts, unlabeled_view
from selfseg.eval.provenance import git_info, provenance
from selfseg.eval.sandbox import Job, MethodRef, raise_reply_error, run_method_process
from selfseg.eval.scoring import MethodOutputError, check_prediction, score_fold
from selfseg.fileio import FileFormatError, atomic_write_text, dumps_json, exclusive_lock, write_json
from selfseg.guard import GroundTruthAccessError
from selfseg.library_log import run_log, summary
from selfseg.method_api import BudgetExceededError, Method
from selfseg.writers import write_inst


def estimated_foreground(video, frame_id: int) -> np.ndarray:
    """bool H×W foreground of ``--foreground plane``: the frame's depth points above the support plane
    (RANSAC with the default :class:`BackgroundConfig`, the methods' own background stage)."""
    from selfseg.method.background import BackgroundConfig, frame_foreground

    return frame_foreground(video.depth_m(frame_id), video.K(frame_id), BackgroundConfig(),
                            f"video {video.video_id} frame {frame_id}")


# evaluate's and evaluate3d's exit status when a fold (or a 3-D row) failed under the budget its config declares
# (record_failure) and the rest finished
EXIT_OVER_BUDGET = 3

# Errors a method's process reports that keep their meaning (one line, exit code 2) in the evaluator.
_INPUT_ERRORS = (MethodOutputError, DatasetError, FileFormatError, ConfigError, FileNotFoundError)


@dataclass
class FoldJob:
    """A fold as the method's process runs it (paths as that process sees them)."""

    label: str  # "<name> fold <k>", for its progress bar
    config: dict | None  # the method's config (None: its defaults)
    root: str  # the dataset folder the method sees
    train_ids: list[str]
    test_frames: dict[str, list[int]]  # test video → its test frames
    fg_bits: dict[str, list[np.ndarray]]  # test video → each test frame's foreground mask, np.packbits
    labeled: tuple[bool, bool]  # whether the training videos, the test videos are opened with their labels
    poses_given: bool
    workdir: str
    stage_root: str | None
    output: str  # where it writes PREDICTION_PNG files
    log: str  # the fold's library log (selfseg.library_log.run_log)
    progress: bool


def _run_fold_job(method_cls: type[Method], job: FoldJob) -> dict:
    """In the method's process: build the method, ``fit`` it, segment the test frames and write their instance
    maps; returns the seconds it took and the training data a method names (``train_data``)."""
    view = Dataset(job.root)
    method = method_cls(None if job.config is None else from_dict(method_cls.config_cls, job.config),
                        Path(job.workdir))
    method.stage_root = None if job.stage_root is None else Path(job.stage_root)
    open_train, open_test = ((lambda v: view.labeled(v)) if labeled else (lambda v: view.video(v, job.poses_given))
                             for labeled in job.labeled)
    with run_log(job.log):
        t0 = time.perf_counter()
        method.fit([open_train(v) for v in job.train_ids])
        fit_s = time.perf_counter() - t0
        segment_s = 0.0
        for vid, frames in tqdm(job.test_frames.items(), desc=f"{job.label}: segment", unit="video",
                                disable=not job.progress):
            size = view.height * view.width
            fg = {f: np.unpackbits(b, count=size).reshape(view.height, view.width).astype(bool)
                  for f, b in zip(frames, job.fg_bits[vid])}
            t0 = time.perf_counter()
            preds = method.segment_video(open_test(vid), frames, fg)
            for f in frames:
                pred = check_prediction(preds.get(f), method_cls.name, vid, f, (view.height, view.width))
                write_inst(Path(job.output) / PREDICTION_PNG.format(video_id=vid, frame_id=f), pred)
            segment_s += time.perf_counter() - t0
    return {"fit_s": fit_s, "segment_s": segment_s, "train_data": getattr(method, "train_data", None)}


def _fold_process(ref: MethodRef, config, dataset: Dataset, view: Path, fold: int, out: Path, options: EvalOptions,
                  train_ids: list[str], test_frames: dict[str, list[int]], fg_bits: dict[str, list[np.ndarray]],
                  output: Path, progress: bool) -> dict:
    """Run a fold's method in its process, given what :func:`~selfseg.eval.mounts.fold_mounts` plans, and return
    its reply."""
    plan = fold_mounts(ref, config, dataset, view, fold, out, options, train_ids, list(test_frames), output)
    job = FoldJob(f"{options.name or ref.name} fold {fold}", plan.config, str(plan.root), train_ids, test_frames,
                  fg_bits, plan.labeled, options.poses_given, str(plan.workdir),
                  None if plan.stage_root is None else str(plan.stage_root), str(output.resolve()), str(plan.log),
                  progress)
    return run_method_process(Job(ref, f"{__name__}:_run_fold_job", job, plan.guard), plan.mounts,
                              [dataset.root.resolve(), out])


def run_fold(method: MethodRef | type[Method], config, dataset: Dataset, fold: int, out: Path,
             options: EvalOptions = EvalOptions(), progress: bool = True) -> dict:
    """Fit, segment, write and score one fold; writes the result JSON and frame sidecar; returns the record.

    ``method``: a :class:`~selfseg.eval.sandbox.MethodRef` (``evaluate``), or a Method subclass already imported
    here (run by its import path, see ``MethodRef.of_class``); ``config``: its config (dataclass or dict; None:
    the defaults). The method runs in its own process (:func:`_fold_process`); if it reached for ground truth,
    a record with ``ground_truth_attempts`` is written to ``REJECTED_JSON`` (nothing is scored) and
    :class:`GroundTruthAccessError` is raised. Its predictions are read once its process has exited, checked,
    scored and written to a staging folder, which replaces each test video's folder only once the fold is
    complete (no stale frames remain). A second process asking for the same run and fold while this one works
    on it gets :class:`~selfseg.fileio.BusyError` before touching anything (``FOLD_LOCK``)."""
    git_info()  # the code as loaded, before the method runs
    ref = method if isinstance(method, MethodRef) else MethodRef.of_class(method)
    if options.method_needs_ground_truth and not ref.user:
        raise ConfigError(f"--method-needs-ground-truth is for a method of your own; {ref.name!r} is registered "
                          "and its registry entry says which labels it gets")
    out = Path(out)
    name = options.name or ref.name
    key = results_key(out, dataset)
    fmt = {"dataset": key, "name": name, "fold": fold}
    with exclusive_lock(out / FOLD_LOCK.format(**fmt), f"fold {fold} of run {name!r}"):
        return _run_fold_locked(ref, config, dataset, fold, out, options, progress, name, fmt)


def _run_fold_locked(ref: MethodRef, config, dataset: Dataset, fold: int, out: Path, options: EvalOptions,
                     progress: bool, name: str, fmt: dict) -> dict:
    """:func:`run_fold`'s work, once its fold lock is held (``fmt``: the fold's path fields)."""
    key = fmt["dataset"]
    train_ids, test_ids = fold_split(dataset, fold)
    pred_dir = out / PREDICTIONS_DIR.format(**fmt)
    staging = pred_dir.parent / f".{pred_dir.name}.fold{fold}.partial"
    output = out / METHOD_OUTPUT_DIR.format(**fmt)
    for d in (staging, output):
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
    log = out / LIBRARY_LOG.format(**fmt)
    log.unlink(missing_ok=True)  # an earlier run's; the method's process starts its own

    test_frames: dict[str, list[int]] = {}
    fg_bits: dict[str, list[np.ndarray]] = {}
    gts: dict[tuple[str, int], np.ndarray] = {}
    for vid in test_ids:
        labeled = dataset.labeled(vid)
        test_frames[vid] = select_test_frames(labeled.frame_ids, options.frame_stride, options.limit)
        for f in test_frames[vid]:
            gts[vid, f] = labeled.inst(f)
        fg_bits[vid] = [np.packbits(gts[vid, f] > 0 if options.foreground == "gt"
                                    else estimated_foreground(labeled, f))
                        for f in test_frames[vid]]
    granted = "train" if options.method_needs_ground_truth else ref.ground_truth
    isolation = {"isolation": ref.isolation, "ground_truth": granted}
    view = unlabeled_view(dataset, out, options.poses_given).resolve()
    try:
        reply = _fold_process(ref, config, dataset, view, fold, out, options, train_ids, test_frames, fg_bits,
                              output, progress)
        logged = summary(log)
        if logged:
            print(f"{name} fold {fold}: {logged}", file=sys.stderr)
        attempts = [str(a) for a in reply.get("ground_truth_attempts") or []]
        if attempts:
            write_json(out / REJECTED_JSON.format(**fmt), {
                **provenance(ref.name, name, config, dataset, "2d"), "fold": fold,
                "options": dataclasses.asdict(options), **isolation, "ground_truth_attempts": attempts})
            raise GroundTruthAccessError(f"method {name!r}, fold {fold}: {len(attempts)} attempt(s), first: "
                                         f"{attempts[0]}")
        try:
            raise_reply_error(reply, ref.name, (BudgetExceededError, *_INPUT_ERRORS), (str(view), str(dataset.root)))
        except BudgetExceededError as e:
            record_failure(out, fmt, {**provenance(ref.name, name, config, dataset, "2d"), "fold": fold,
                                       "n_folds": N_FOLDS, "train_videos": train_ids, "test_videos": test_ids,
                                       "options": dataclasses.asdict(options), **isolation}, e)
            raise

        evaluator, score_s = score_fold(output, ref.name, f"{name} fold {fold}", test_frames, gts,
                                        (dataset.height, dataset.width), staging, options, progress)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    finally:
        shutil.rmtree(output, ignore_errors=True)
    result = evaluator.evaluate()

    n_frames = len(gts)
    record = {
        **provenance(ref.name, name, config, dataset, "2d"),
        "fold": fold,
        "n_folds": N_FOLDS,
        "train_videos": train_ids,
        "test_videos": test_ids,
        "options": dataclasses.asdict(options),
        **isolation,
        **result,
        "timings": {"fit_s": round(float(reply.get("fit_s", 0.0)), 4),
                    "ms_per_frame": round(1000 * float(reply.get("segment_s", 0.0)) / max(n_frames, 1), 4),
                    "score_ms_per_frame": round(1000 * score_s / max(n_frames, 1), 4)},
        "predictions_dir": str(pred_dir.resolve()),
        "ground_truth_attempts": [],
    }
    record["dataset"]["key"] = key
    if isinstance(reply.get("train_data"), dict):  # hook: a method trained on another dataset names it in fit
        record["train_data"] = reply["train_data"]
    for vid in test_ids:  # swap in this fold's videos: no frame of an earlier run stays behind
        shutil.rmtree(pred_dir / vid, ignore_errors=True)
        pred_dir.mkdir(parents=True, exist_ok=True)
        os.replace(staging / vid, pred_dir / vid)
    shutil.rmtree(staging, ignore_errors=True)
    write_result(out, record, evaluator.frames)
    return record


def record_failure(out: Path, fmt: dict, record: dict, error: BudgetExceededError) -> Path:
    """Write the failure record of a fold (or a 3-D row) whose method passed its budget: ``record`` holds the
    provenance fields of a result record; nothing is scored, and an earlier run's scores of the fold are removed
    (the fold's outcome is now this failure). Returns its path (``FAILED_JSON``)."""
    path = Path(out) / FAILED_JSON.format(**fmt)
    record["dataset"]["key"] = fmt["dataset"]
    write_json(path, {**record, "failure": {"kind": "budget", "message": str(error)}})
    for stale in (SCORES_JSON, FRAMES_JSONL):
        (Path(out) / stale.format(**fmt)).unlink(missing_ok=True)
    return path


def write_result(out: Path, record: dict, frames: list[dict]) -> Path:
    """Atomically write a fold's result record and its per-frame (or per-video) sidecar; returns the JSON path.

    ``record`` needs at least the :func:`provenance` fields, ``fold``, ``metrics`` (with
    ``n_frames``), ``per_video``, ``ci95`` and ``timings`` (``fit_s``, ``ms_per_frame``): the 3-D
    (Table II) results of later stages use the same writer with ``task="3d"``. A failure record of the same fold
    (:func:`record_failure`) is removed.
    """
    fmt = {"dataset": record["dataset"].get("key", record["dataset"]["name"]), "name": record["name"],
           "fold": record["fold"]}
    path = Path(out) / SCORES_JSON.format(**fmt)
    write_json(path, record)
    atomic_write_text(Path(out) / FRAMES_JSONL.format(**fmt), "".join(dumps_json(f, indent=None) + "\n" for f in frames))
    (Path(out) / FAILED_JSON.format(**fmt)).unlink(missing_ok=True)  # an earlier run's failure of this fold, if any
    return path
