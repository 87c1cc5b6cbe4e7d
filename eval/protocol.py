"""The paper's evaluation protocol: 3-fold cross-validation over videos, every 10th test frame.

For each fold the method is built fresh, ``fit`` on the fold's training videos and asked to
segment the test frames of its held-out videos, given the ground-truth foreground masks.
Self-supervised methods get unlabeled :class:`~selfseg.dataset.Video` objects and run under
:func:`~selfseg.dataset.ground_truth_forbidden`; only methods declaring ``needs_ground_truth``
get :class:`~selfseg.dataset.LabeledVideo` objects. Predictions are written to disk, then
scored from disk. Output layout under ``OUT`` (default ``results/``)::

    scores/<dataset>/<name>/fold<k>.json          result record (schema below, SCHEMA_VERSION)
    scores/<dataset>/<name>/fold<k>.frames.jsonl  one line of metrics per test frame
    predictions/<name>/<dataset>/<video_id>/<frame_id:06d>.png   uint16 instance maps
    work/<name>/<dataset>/fold<k>/                the method's cache (``Method.workdir``)

``<name>`` is the method name unless ``--name`` gives a variant name. Each video is a test
video in exactly one fold, so ``predictions/<name>/<dataset>/`` is a valid folder for the
``external`` method (re-scoring never re-runs a method).
"""
from __future__ import annotations

import contextlib
import dataclasses
import datetime
import importlib.metadata
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from selfseg.baselines.base import Method
from selfseg.config import config_hash, to_dict
from selfseg.dataset import FORMAT_VERSION, Dataset, DatasetError, ground_truth_forbidden, read_inst, write_inst
from selfseg.eval.aggregate import N_BOOTSTRAP, BOOTSTRAP_SEED, SegmentationEvaluator
from selfseg.fileio import atomic_write_text, dumps_json, write_json

SCHEMA_VERSION = 1
N_FOLDS = 3
SCORES_JSON = "scores/{dataset}/{name}/fold{fold}.json"
FRAMES_JSONL = "scores/{dataset}/{name}/fold{fold}.frames.jsonl"
PREDICTIONS_DIR = "predictions/{name}/{dataset}"
WORK_DIR = "work/{name}/{dataset}/fold{fold}"
VERSIONED_PACKAGES = ("selfseg", "numpy", "scipy", "torch", "open3d-cpu", "opencv-python-headless", "trimesh")


class MethodOutputError(ValueError):
    """A method returned something that is not a valid instance map for a requested frame."""


@dataclass
class EvalOptions:
    """Protocol options; all are recorded in every result file."""

    folds: tuple[int, ...] = (0, 1, 2)
    frame_stride: int = 10  # test frames: every frame_stride-th frame of a held-out video, from frame 0
    limit: int | None = None  # at most this many test frames per held-out video (quick runs)
    name: str | None = None  # result name (default: the method name), for variants and external runs
    poses_given: bool = False  # give methods the ground-truth camera poses (ablation)
    # Foreground given to methods: "gt" (the paper's protocol) or "plane" (estimated from each frame's depth
    # by removing the support plane, as a robot would; scoring still uses the ground-truth foreground)
    foreground: str = "gt"
    n_boot: int = N_BOOTSTRAP
    seed: int = BOOTSTRAP_SEED  # bootstrap seed

    def __post_init__(self):
        if self.frame_stride < 1:
            raise ValueError(f"frame_stride must be ≥ 1, got {self.frame_stride}")
        if self.limit is not None and self.limit < 1:
            raise ValueError(f"limit must be ≥ 1, got {self.limit}")
        if self.foreground not in ("gt", "plane"):
            raise ValueError(f"foreground must be 'gt' or 'plane', got {self.foreground!r}")
        bad = [k for k in self.folds if not 0 <= k < N_FOLDS]
        if bad or not self.folds:
            raise ValueError(f"folds must be a non-empty subset of 0..{N_FOLDS - 1}, got {list(self.folds)}")


def make_folds(dataset: Dataset, n_folds: int = N_FOLDS) -> list[list[str]]:
    """Test videos of each fold: ``dataset_info.json['folds']`` if stored, else a permutation
    seeded by the dataset's seed, split into ``n_folds`` near-equal parts (each list sorted)."""
    stored = dataset.info.get("folds")
    if stored is not None:
        folds = [sorted(str(v) for v in f) for f in stored]
        flat = [v for f in folds for v in f]
        if len(folds) != n_folds or sorted(flat) != dataset.video_ids:
            raise DatasetError(f"{dataset.root / 'dataset_info.json'}: 'folds' must split the {len(dataset.video_ids)} "
                               f"videos into {n_folds} disjoint lists")
        return folds
    if len(dataset.video_ids) < n_folds:
        raise DatasetError(f"{dataset.root}: {n_folds}-fold cross-validation needs at least {n_folds} videos, "
                           f"found {len(dataset.video_ids)}")
    order = np.random.default_rng(dataset.seed).permutation(len(dataset.video_ids))
    return [sorted(dataset.video_ids[i] for i in part) for part in np.array_split(order, n_folds)]


def fold_split(dataset: Dataset, fold: int) -> tuple[list[str], list[str]]:
    """(training video ids, test video ids) of a fold; the two never share a video."""
    test = make_folds(dataset)[fold]
    return [v for v in dataset.video_ids if v not in test], test


def select_test_frames(frame_ids: list[int], stride: int, limit: int | None) -> list[int]:
    """Every ``stride``-th frame (from the first), at most ``limit`` of them."""
    return list(frame_ids[::stride][:limit])


def git_info() -> dict:
    """Commit of the selfseg checkout and whether tracked files differ from it."""
    repo = Path(__file__).resolve().parents[1]
    try:
        commit = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10, check=True).stdout.strip() != ""
        return {"commit": commit, "dirty": dirty}
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}


def package_versions() -> dict:
    out = {}
    for pkg in VERSIONED_PACKAGES:
        try:
            out[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            out[pkg] = None
    return out


def _check_prediction(pred, name: str, video_id: str, frame_id: int, shape: tuple[int, int]) -> np.ndarray:
    if pred is None:
        raise MethodOutputError(f"method {name!r} returned no prediction for video {video_id} frame {frame_id}")
    pred = np.asarray(pred)
    if pred.shape != shape or not np.issubdtype(pred.dtype, np.integer):
        raise MethodOutputError(f"method {name!r}, video {video_id} frame {frame_id}: expected an integer "
                                f"{shape[1]}×{shape[0]} instance map, got {pred.dtype} {pred.shape}")
    return pred


def estimated_foreground(video, frame_id: int) -> np.ndarray:
    """bool H×W foreground of ``--foreground plane``: the frame's depth points above the support plane
    (RANSAC with the default :class:`BackgroundConfig`, the methods' own background stage)."""
    from selfseg.baselines.semantic_instances import frame_foreground
    from selfseg.method.background import BackgroundConfig

    return frame_foreground(video, frame_id, BackgroundConfig())


def run_fold(method_cls: type[Method], config, dataset: Dataset, fold: int, out: Path,
             options: EvalOptions = EvalOptions(), progress: bool = True) -> dict:
    """Fit, segment, write and score one fold; writes the result JSON and frame sidecar; returns the record."""
    out = Path(out)
    name = options.name or method_cls.name
    fmt = {"dataset": dataset.name, "name": name, "fold": fold}
    train_ids, test_ids = fold_split(dataset, fold)
    workdir = out / WORK_DIR.format(**fmt)
    workdir.mkdir(parents=True, exist_ok=True)
    pred_dir = out / PREDICTIONS_DIR.format(**fmt)
    gt_allowed = method_cls.needs_ground_truth

    def open_video(vid: str):
        return dataset.labeled(vid) if gt_allowed else dataset.video(vid, poses_given=options.poses_given)

    def guard():
        return contextlib.nullcontext() if gt_allowed else ground_truth_forbidden(dataset.root)

    method = method_cls(config, workdir)
    t0 = time.perf_counter()
    with guard():
        method.fit([open_video(v) for v in train_ids])
    fit_s = time.perf_counter() - t0

    seg_s = 0.0
    n_frames = 0
    written: list[tuple[str, int]] = []
    gts: dict[tuple[str, int], np.ndarray] = {}
    for vid in tqdm(test_ids, desc=f"{name} fold {fold}: segment", unit="video", disable=not progress):
        labeled = dataset.labeled(vid)
        frames = select_test_frames(labeled.frame_ids, options.frame_stride, options.limit)
        fg = {}
        for f in frames:
            gts[vid, f] = labeled.inst(f)
            fg[f] = gts[vid, f] > 0 if options.foreground == "gt" else estimated_foreground(labeled, f)
        video = open_video(vid)
        t0 = time.perf_counter()
        with guard():
            preds = method.segment_video(video, frames, fg)
        seg_s += time.perf_counter() - t0
        n_frames += len(frames)
        for f in frames:
            pred = _check_prediction(preds.get(f), name, vid, f, (dataset.height, dataset.width))
            write_inst(pred_dir / f"{vid}/{f:06d}.png", pred)
            written.append((vid, f))

    evaluator = SegmentationEvaluator(n_boot=options.n_boot, seed=options.seed)
    t0 = time.perf_counter()
    for vid, f in tqdm(written, desc=f"{name} fold {fold}: score", unit="frame", disable=not progress):
        evaluator.process(vid, f, read_inst(pred_dir / f"{vid}/{f:06d}.png"), gts[vid, f])
    score_s = time.perf_counter() - t0
    result = evaluator.evaluate()

    record = {
        **provenance(method_cls.name, name, config, dataset, "2d"),
        "fold": fold,
        "n_folds": N_FOLDS,
        "train_videos": train_ids,
        "test_videos": test_ids,
        "options": dataclasses.asdict(options),
        **result,
        "timings": {"fit_s": round(fit_s, 4), "ms_per_frame": round(1000 * seg_s / max(n_frames, 1), 4),
                    "score_ms_per_frame": round(1000 * score_s / max(n_frames, 1), 4)},
        "predictions_dir": str(pred_dir.resolve()),
    }
    if getattr(method, "train_data", None):  # hook: a method trained on another dataset names it (a dict) in fit
        record["train_data"] = method.train_data
    write_result(out, record, evaluator.frames)
    return record


def provenance(method: str, name: str, config, dataset: Dataset, task: str) -> dict:
    """The fields every result record starts with: schema, task ("2d" or "3d"), method, config, dataset, code."""
    return {
        "schema_version": SCHEMA_VERSION,
        "task": task,
        "name": name,
        "method": method,
        "config": to_dict(config),
        "config_hash": config_hash(config),
        "dataset": {"name": dataset.name, "root": str(dataset.root.resolve()),
                    "format_version": dataset.info.get("format_version", FORMAT_VERSION),
                    "content_hash": dataset.content_hash(), "n_videos": len(dataset.video_ids)},
        "git": git_info(),
        "versions": package_versions(),
        "created_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


def write_result(out: Path, record: dict, frames: list[dict]) -> Path:
    """Atomically write a fold's result record and its per-frame (or per-video) sidecar; returns the JSON path.

    ``record`` needs at least the :func:`provenance` fields, ``fold``, ``metrics`` (with
    ``n_frames``), ``per_video``, ``ci95`` and ``timings`` (``fit_s``, ``ms_per_frame``): the 3-D
    (Table II) results of later stages use the same writer with ``task="3d"``.
    """
    fmt = {"dataset": record["dataset"]["name"], "name": record["name"], "fold": record["fold"]}
    path = Path(out) / SCORES_JSON.format(**fmt)
    write_json(path, record)
    atomic_write_text(Path(out) / FRAMES_JSONL.format(**fmt), "".join(dumps_json(f, indent=None) + "\n" for f in frames))
    return path
