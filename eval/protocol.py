"""The paper's evaluation protocol: 3-fold cross-validation over videos, every 10th test frame.

For each fold the method is built fresh, ``fit`` on the fold's training videos and asked to
segment the test frames of its held-out videos, given the ground-truth foreground masks.
Every method runs in its own process, in a sandbox (:mod:`selfseg.eval.sandbox`) that holds the fold's
inputs only: the videos of a copy of the dataset without ground truth (:func:`unlabeled_view`), read as
unlabeled :class:`~selfseg.dataset.Video` objects. Only registered methods whose registry entry gives them
labels (and a user's method run with ``--method-needs-ground-truth``) get the fold's *training* videos with
their labels, as :class:`~selfseg.dataset.LabeledVideo` objects; the test videos' labels only the oracle.
The method writes its predictions into a folder of its own; the evaluator reads them once the method's
process has exited, checks them, scores them and files them. Output layout under ``OUT`` (default ``results/``)::

    scores/<dataset>/<name>/fold<k>.json          result record (schema below, SCHEMA_VERSION)
    scores/<dataset>/<name>/fold<k>.frames.jsonl  one line of metrics per test frame
    predictions/<name>/<dataset>/<video_id>/<frame_id:06d>.png   uint16 instance maps
    work/<name>/<dataset>/fold<k>/                the method's cache (``Method.workdir``)
    work/_views/<content hash>-<poses>/<folder>/  the unlabeled copy of the dataset that methods see
    work/_stages/<content hash>-<poses>/          label-free registered methods' per-video stage caches (``Method.stage_root``)
    work/<name>/<dataset>/fold<k>/_stages/        the stage cache of a registered method given labels (its fold's own)
    rejected/<dataset>/<name>/fold<k>.json        a fold whose method reached for ground truth (not scored)
    replaced/<dataset>/<name>.<pid>/              ``evaluate --replace``: the old run, until the new one finished

``<name>`` is the method name unless ``--name`` gives a variant name; ``<dataset>`` is the dataset's name,
or ``<name>-<content hash>`` when results of another dataset of that name are already there
(:func:`results_key`), so two datasets never mix, and a run name holds one run: ``evaluate`` refuses a run
whose method, config or options differ from those already filed under its name (:func:`run_conflict`)
unless ``--replace`` is given. Each video is a test
video in exactly one fold, so ``predictions/<name>/<dataset>/`` is a valid folder for the
``external`` method (re-scoring never re-runs a method).
"""
from __future__ import annotations

import dataclasses
import datetime
import functools
import importlib.metadata
import os
import shutil
import stat
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from selfseg.config import ConfigError, config_hash, from_dict, to_dict
from selfseg.dataset import (DATASET_INFO, DEPTH, FORMAT_VERSION, RGB, SCENE_CAMERA, VIDEO_DIR, Dataset, DatasetError,
                             read_inst)
from selfseg.eval.aggregate import N_BOOTSTRAP, BOOTSTRAP_SEED, SegmentationEvaluator
from selfseg.eval.sandbox import Job, MethodRef, Mount, check_mounts, raise_reply_error, run_method_process
from selfseg.fileio import (FileFormatError, atomic_dir, atomic_write_text, dumps_json, exclusive_lock, read_json,
                            write_json)
from selfseg.guard import GroundTruthAccessError, guard_paths
from selfseg.method_api import Method
from selfseg.writers import write_inst

SCHEMA_VERSION = 1
N_FOLDS = 3
SCORES_DIR = "scores"
RUN_SCORES_DIR = SCORES_DIR + "/{dataset}/{name}"  # one run's folds
SCORES_JSON = RUN_SCORES_DIR + "/fold{fold}.json"
FRAMES_JSONL = RUN_SCORES_DIR + "/fold{fold}.frames.jsonl"
PREDICTIONS_DIR = "predictions/{name}/{dataset}"
PREDICTION_PNG = "{video_id}/{frame_id:06d}.png"  # one frame's instance map in PREDICTIONS_DIR (and in `external`'s input)
WORK_DIR = "work/{name}/{dataset}/fold{fold}"
STAGES_DIR = "work/_stages"  # per-video stage caches shared by every run and fold in OUT (evaluate3d's stage_root)
STAGE_ROOT_DIR = "work/_stages/{content_hash}-{poses}"  # label-free registered methods' stage_root under evaluate
LABELED_STAGE_ROOT_DIR = WORK_DIR + "/_stages"  # the stage_root of a registered method given labels: its fold's own
METHOD_OUTPUT_DIR = "predictions/{name}/.{dataset}.fold{fold}.method"  # where the method's process writes predictions
REJECTED_JSON = "rejected/{dataset}/{name}/fold{fold}.json"  # a fold whose method reached for ground truth
FOLD_LOCK = "work/{name}/{dataset}/.fold{fold}.lock"  # held while a process runs this fold (fileio.exclusive_lock)
VIEW_DIR = "work/_views/{content_hash}-{poses}/{folder}"  # the unlabeled copy of a dataset that methods see
REPLACED_DIR = "replaced/{dataset}/{name}.{pid}"  # evaluate --replace: the old run, deleted once the new one finished
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
    # a user's method (``package.module:Class``) is given its training videos' labels (never the test videos')
    method_needs_ground_truth: bool = False

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
            raise DatasetError(f"{dataset.root / DATASET_INFO}: 'folds' must split the {len(dataset.video_ids)} "
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


@functools.cache
def git_info() -> dict:
    """Commit of the selfseg checkout and whether tracked files differ from it, as this process first saw them
    (the code it loaded): the run functions ask before any work, so a commit made while a run trains does not
    relabel its results."""
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
    lo, hi = int(pred.min(initial=0)), int(pred.max(initial=0))
    if lo < 0 or hi > 65535:
        raise MethodOutputError(f"method {name!r}, video {video_id} frame {frame_id}: instance ids must lie in "
                                f"[0, 65535], got {lo}..{hi}")
    return pred


def estimated_foreground(video, frame_id: int) -> np.ndarray:
    """bool H×W foreground of ``--foreground plane``: the frame's depth points above the support plane
    (RANSAC with the default :class:`BackgroundConfig`, the methods' own background stage)."""
    from selfseg.method.background import BackgroundConfig, frame_foreground

    return frame_foreground(video.depth_m(frame_id), video.K(frame_id), BackgroundConfig(),
                            f"video {video.video_id} frame {frame_id}")


def unlabeled_view(dataset: Dataset, out: Path, poses_given: bool) -> Path:
    """The dataset as a method may see it, built once under ``out`` (atomically): ``dataset_info.json``
    and, per video, ``rgb/`` and ``depth/`` (hard links, copies across file systems) and
    ``scene_camera.json`` with the camera poses set to identity unless ``poses_given``. No ground
    truth and no object models are in it, and its folder has the dataset folder's name."""
    view = Path(out) / VIEW_DIR.format(content_hash=dataset.content_hash(), poses="poses" if poses_given else "noposes",
                                       folder=dataset.root.resolve().name)
    if view.is_dir():
        return view
    try:
        with atomic_dir(view) as tmp:
            shutil.copyfile(dataset.root / DATASET_INFO, tmp / DATASET_INFO)
            for vid in dataset.video_ids:
                cams = read_json(dataset.root / SCENE_CAMERA.format(video_id=vid))
                for key in cams:
                    for template in (RGB, DEPTH):
                        rel = template.format(video_id=vid, frame_id=int(key))
                        (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
                        try:
                            os.link(dataset.root / rel, tmp / rel)
                        except FileNotFoundError:
                            raise DatasetError(f"{dataset.root / rel}: missing file") from None
                        except OSError:  # another file system, or not allowed to link: copy
                            shutil.copyfile(dataset.root / rel, tmp / rel)
                    if not poses_given:
                        cams[key] = {**cams[key], "cam_R_w2c": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                                     "cam_t_w2c": [0.0, 0.0, 0.0]}
                write_json(tmp / SCENE_CAMERA.format(video_id=vid), cams)
    except OSError:  # another fold (a parallel task) finished the same view first: it is complete, keep it
        if not view.is_dir():
            raise
    return view


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
            pred = _check_prediction(preds.get(f), method_cls.name, vid, f, (view.height, view.width))
            write_inst(Path(job.output) / PREDICTION_PNG.format(video_id=vid, frame_id=f), pred)
        segment_s += time.perf_counter() - t0
    return {"fit_s": fit_s, "segment_s": segment_s, "train_data": getattr(method, "train_data", None)}


def _method_prediction(output: Path, name: str, video_id: str, frame_id: int, shape: tuple[int, int]) -> np.ndarray:
    """A prediction the method's process wrote into ``output``, read only if it is a plain file in a plain folder
    (a link could point the evaluator at ground truth the method never saw; a pipe would block it)."""
    path = output / PREDICTION_PNG.format(video_id=video_id, frame_id=frame_id)
    for p, plain in ((path.parent, stat.S_ISDIR), (path, stat.S_ISREG)):
        try:
            mode = os.lstat(p).st_mode
        except FileNotFoundError:
            raise MethodOutputError(f"method {name!r} wrote no prediction for video {video_id} frame {frame_id}") \
                from None
        if not plain(mode):
            raise MethodOutputError(f"method {name!r}: its prediction {p.relative_to(output)} is not a plain "
                                    f"{'folder' if plain is stat.S_ISDIR else 'file'}")
    pred = read_inst(path)
    if pred.shape != shape:
        raise MethodOutputError(f"method {name!r}, video {video_id} frame {frame_id}: expected a {shape[1]}×{shape[0]} "
                                f"instance map, got {pred.shape[1]}×{pred.shape[0]}")
    return pred


def method_stage_root(out: Path, dataset: Dataset, poses_given: bool, granted: str, fmt: dict) -> Path:
    """A registered method's stage root (absolute) for one fold. Given no labels: ``STAGE_ROOT_DIR``, shared by
    every label-free registered method and fold that sees the same videos. Given labels: its fold's own
    ``LABELED_STAGE_ROOT_DIR``, as its work folder is, so that nothing it writes reaches a label-free method or
    another fold; its videos' camera files then hold the dataset's poses, which the unlabeled view strips, so
    its stage keys differ anyway, and a shared folder would be rebuilt under a reader's feet by each side."""
    if granted != "none":
        return (out / LABELED_STAGE_ROOT_DIR.format(**fmt)).resolve()
    return (out / STAGE_ROOT_DIR.format(content_hash=dataset.content_hash(),
                                        poses="poses" if poses_given else "noposes")).resolve()


def _fold_process(ref: MethodRef, config, dataset: Dataset, view: Path, fold: int, out: Path, options: EvalOptions,
                  train_ids: list[str], test_frames: dict[str, list[int]], fg_bits: dict[str, list[np.ndarray]],
                  output: Path, progress: bool) -> dict:
    """Run a fold's method in its process and return its reply. What it is given (``ground truth``: the labels
    granted, see :data:`selfseg.eval.sandbox.GROUND_TRUTH`):

    * the dataset as ``view`` (:func:`unlabeled_view`) at the view's path: ``dataset_info.json`` and every video's folder,
      read-only; the training videos' folders (labels included) from the dataset itself when labels are
      granted, the test videos' too only for "all" (the oracle);
    * its work folder, writable: the run's ``work/<name>/<dataset>/`` (its folds share it) when it is given no
      labels, else only the fold's (no fold sees labels another fold was given, which include its test videos');
    * a registered method: its stage root (:func:`method_stage_root`, writable) and the folders its config names
      (``registry.CONFIG_DIRS``); a user's method: no stage root (it caches in its work folder);
    * ``output``, writable, for its predictions.

    Unsandboxed, the same paths are given to a plain child process; it reads the real dataset when given labels."""
    granted = "train" if options.method_needs_ground_truth else ref.ground_truth
    test_ids = list(test_frames)
    real = dataset.root.resolve()
    fmt = {"name": options.name or ref.name, "dataset": results_key(out, dataset), "fold": fold}
    workdir = (out / WORK_DIR.format(**fmt)).resolve()
    workroot = workdir.parent if granted == "none" else workdir
    stage_root = None if ref.user else method_stage_root(out, dataset, options.poses_given, granted, fmt)
    config_dict = None if config is None else to_dict(config)
    config_dirs = []
    for key, mode in ref.config_dirs:
        value = (config_dict or {}).get(key)
        if value and mode == "rw":
            Path(value).mkdir(parents=True, exist_ok=True)
        if value and os.path.exists(value):
            config_dirs.append(Mount.same(value, writable=mode == "rw"))
    check_mounts(config_dirs, [real, out], [real])
    workdir.mkdir(parents=True, exist_ok=True)
    writable = [Mount.same(p, writable=True) for p in (workroot, stage_root, output.resolve()) if p is not None]
    for m in writable:
        Path(m.src).mkdir(parents=True, exist_ok=True)
    check_mounts(writable, [real], [real])
    labeled = {v: granted == "all" or (granted == "train" and v in train_ids) for v in dataset.video_ids}
    mounts = [Mount(str(view / DATASET_INFO), str(view / DATASET_INFO)), *writable, *config_dirs]
    mounts += [Mount(str((real if labeled[v] else view) / VIDEO_DIR.format(video_id=v)),
                     str(view / VIDEO_DIR.format(video_id=v))) for v in dataset.video_ids]
    # unsandboxed, a method given labels reads the dataset itself
    root = view if ref.sandboxed or granted == "none" else real
    guard = (guard_paths(real, view) if granted == "none" else
             guard_paths(*(r / VIDEO_DIR.format(video_id=v) for r in (real, view) for v in test_ids))
             if granted == "train" else [])
    job = FoldJob(f"{fmt['name']} fold {fold}", config_dict, str(root), train_ids, test_frames, fg_bits,
                  (granted != "none", granted == "all"), options.poses_given, str(workdir),
                  None if stage_root is None else str(stage_root), str(output.resolve()), progress)
    return run_method_process(Job(ref, f"{__name__}:_run_fold_job", job, guard), mounts, [real, out])


def results_key(out: Path, dataset: Dataset) -> str:
    """The folder name a dataset's results are filed under in ``out``: its name, or ``<name>-<content hash>``
    when ``scores/<name>/`` already holds results of a different dataset with the same name."""
    content = dataset.content_hash()
    for path in sorted((Path(out) / SCORES_DIR / dataset.name).glob("*/fold*.json")):
        if read_json(path).get("dataset", {}).get("content_hash") != content:
            return f"{dataset.name}-{content[:8]}"
    return dataset.name


def _resume_key(record: dict) -> dict:
    options = {k: v for k, v in record["options"].items() if k != "folds"}
    return {"method": record["method"], "config_hash": record["config_hash"], "options": options,
            "dataset": record["dataset"]["content_hash"], "commit": record["git"]["commit"]}


def _differences(old, new, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two JSON-like dicts, as ``key old → new``."""
    if isinstance(old, dict) and isinstance(new, dict):
        return [d for k in sorted(set(old) | set(new), key=str)
                for d in _differences(old.get(k), new.get(k), f"{prefix}{k}.")]
    return [] if old == new else [f"{prefix[:-1]} {old!r} → {new!r}"]


def run_conflict(out: Path, dataset: Dataset, method: str, config, options: EvalOptions) -> str | None:
    """Why a run with these settings would mix with the run already filed under its name in ``out`` (another
    method, config or protocol options: each fold of a run must share them), or None. The dataset is not
    compared: another dataset's content is filed under a key of its own (:func:`results_key`)."""
    name = options.name or method
    new = {"method": method, "config": to_dict(config),
           "options": {k: v for k, v in dataclasses.asdict(options).items() if k != "folds"}}
    for path in sorted((Path(out) / RUN_SCORES_DIR.format(dataset=results_key(out, dataset), name=name)).glob("fold*.json")):
        rec = read_json(path)
        old = {"method": rec.get("method"), "config": rec.get("config"),
               "options": {k: v for k, v in rec.get("options", {}).items() if k != "folds"}}
        diff = _differences(old, new)
        if diff:
            more = f" and {len(diff) - 3} more" if len(diff) > 3 else ""
            return f"{path}: run {name!r} was made with other settings ({'; '.join(diff[:3])}{more})"
    return None


def retire_run(out: Path, dataset: Dataset, name: str) -> Path:
    """Move run ``name``'s scores and predictions for ``dataset`` out of the way (renames, so no fold of the old
    run stays beside the new one's); returns the folder they went to, to delete once the new run finished."""
    fmt = {"dataset": results_key(out, dataset), "name": name}
    trash = Path(out) / REPLACED_DIR.format(**fmt, pid=os.getpid())
    for kind, folder in (("scores", Path(out) / RUN_SCORES_DIR.format(**fmt)),
                         ("predictions", Path(out) / PREDICTIONS_DIR.format(**fmt))):
        if folder.exists():
            trash.mkdir(parents=True, exist_ok=True)
            os.replace(folder, trash / kind)
    return trash


def finished_fold(method_cls: MethodRef | type[Method], config, dataset: Dataset, fold: int, out: Path,
                  options: EvalOptions = EvalOptions()) -> dict | None:
    """The stored record of this fold if an earlier run had the same method, config, options, dataset
    content and commit and its predictions are all in place (``evaluate`` resumes with it), else None."""
    fmt = {"dataset": results_key(out, dataset), "name": options.name or method_cls.name, "fold": fold}
    path = Path(out) / SCORES_JSON.format(**fmt)
    if not path.is_file():
        return None
    record = read_json(path)
    want = {"method": method_cls.name, "config_hash": config_hash(config),
            "options": {k: v for k, v in dataclasses.asdict(options).items() if k != "folds"},
            "dataset": dataset.content_hash(), "commit": git_info()["commit"]}
    pred_dir = Path(out) / PREDICTIONS_DIR.format(**fmt)
    frames = [(v, f) for v in record.get("test_videos", []) for f in select_test_frames(
        dataset.video(v).frame_ids, options.frame_stride, options.limit)]
    if want["commit"] is None or _resume_key(record) != want or \
            not all((pred_dir / PREDICTION_PNG.format(video_id=v, frame_id=f)).is_file() for v, f in frames):
        return None
    return record


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
        attempts = [str(a) for a in reply.get("ground_truth_attempts") or []]
        if attempts:
            write_json(out / REJECTED_JSON.format(**fmt), {
                **provenance(ref.name, name, config, dataset, "2d"), "fold": fold,
                "options": dataclasses.asdict(options), **isolation, "ground_truth_attempts": attempts})
            raise GroundTruthAccessError(f"method {name!r}, fold {fold}: {len(attempts)} attempt(s), first: "
                                         f"{attempts[0]}")
        raise_reply_error(reply, ref.name, _INPUT_ERRORS, (str(view), str(dataset.root)))

        evaluator = SegmentationEvaluator(n_boot=options.n_boot, seed=options.seed)
        score_s = 0.0
        for vid, frames in test_frames.items():
            for f in tqdm(frames, desc=f"{name} fold {fold}: score {vid}", unit="frame", disable=not progress):
                t0 = time.perf_counter()
                pred = _method_prediction(output, ref.name, vid, f, (dataset.height, dataset.width))
                evaluator.process(vid, f, pred, gts[vid, f])
                score_s += time.perf_counter() - t0
                write_inst(staging / PREDICTION_PNG.format(video_id=vid, frame_id=f), pred)
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
        "git": dict(git_info()),
        "versions": package_versions(),
        "created_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


def write_result(out: Path, record: dict, frames: list[dict]) -> Path:
    """Atomically write a fold's result record and its per-frame (or per-video) sidecar; returns the JSON path.

    ``record`` needs at least the :func:`provenance` fields, ``fold``, ``metrics`` (with
    ``n_frames``), ``per_video``, ``ci95`` and ``timings`` (``fit_s``, ``ms_per_frame``): the 3-D
    (Table II) results of later stages use the same writer with ``task="3d"``.
    """
    fmt = {"dataset": record["dataset"].get("key", record["dataset"]["name"]), "name": record["name"],
           "fold": record["fold"]}
    path = Path(out) / SCORES_JSON.format(**fmt)
    write_json(path, record)
    atomic_write_text(Path(out) / FRAMES_JSONL.format(**fmt), "".join(dumps_json(f, indent=None) + "\n" for f in frames))
    return path
