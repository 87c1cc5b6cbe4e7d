"""The paper's evaluation protocol: 3-fold cross-validation over videos, every 10th test frame.

For each fold the method is built fresh, ``fit`` on the fold's training videos and asked to
segment the test frames of its held-out videos, given the ground-truth foreground masks.
Every method runs in its own process (:class:`MethodSandbox`): self-supervised methods get
unlabeled :class:`~selfseg.dataset.Video` objects of a copy of the dataset without ground truth
(:func:`unlabeled_view`) and never its path; only methods declaring ``needs_ground_truth`` get
:class:`~selfseg.dataset.LabeledVideo` objects. Predictions are written to disk, then scored
from disk. Output layout under ``OUT`` (default ``results/``)::

    scores/<dataset>/<name>/fold<k>.json          result record (schema below, SCHEMA_VERSION)
    scores/<dataset>/<name>/fold<k>.frames.jsonl  one line of metrics per test frame
    predictions/<name>/<dataset>/<video_id>/<frame_id:06d>.png   uint16 instance maps
    work/<name>/<dataset>/fold<k>/                the method's cache (``Method.workdir``)
    work/_views/<content hash>-<poses>/<folder>/  the unlabeled copy of the dataset that methods see
    rejected/<dataset>/<name>/fold<k>.json        a fold whose method reached for ground truth (not scored)

``<name>`` is the method name unless ``--name`` gives a variant name; ``<dataset>`` is the dataset's name,
or ``<name>-<content hash>`` when results of another dataset of that name are already there
(:func:`results_key`), so two datasets never mix. Each video is a test
video in exactly one fold, so ``predictions/<name>/<dataset>/`` is a valid folder for the
``external`` method (re-scoring never re-runs a method).
"""
from __future__ import annotations

import dataclasses
import datetime
import importlib.metadata
import multiprocessing
import os
import pickle
import shutil
import signal
import subprocess
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from selfseg.config import ConfigError, config_hash, to_dict
from selfseg.dataset import (DATASET_INFO, DEPTH, FORMAT_VERSION, RGB, SCENE_CAMERA, Dataset, DatasetError,
                             GroundTruthAccessError, dataset_identity, ground_truth_attempts, read_inst,
                             sandbox_ground_truth_guard, write_inst)
from selfseg.eval.aggregate import N_BOOTSTRAP, BOOTSTRAP_SEED, SegmentationEvaluator
from selfseg.fileio import FileFormatError, atomic_dir, atomic_write_text, dumps_json, read_json, write_json
from selfseg.method_api import Method

SCHEMA_VERSION = 1
N_FOLDS = 3
SCORES_JSON = "scores/{dataset}/{name}/fold{fold}.json"
FRAMES_JSONL = "scores/{dataset}/{name}/fold{fold}.frames.jsonl"
PREDICTIONS_DIR = "predictions/{name}/{dataset}"
PREDICTION_PNG = "{video_id}/{frame_id:06d}.png"  # one frame's instance map in PREDICTIONS_DIR (and in `external`'s input)
WORK_DIR = "work/{name}/{dataset}/fold{fold}"
STAGES_DIR = "work/_stages"  # per-video stage caches shared by every run and fold in OUT (methods' stage_root)
REJECTED_JSON = "rejected/{dataset}/{name}/fold{fold}.json"  # a fold whose method reached for ground truth
VIEW_DIR = "work/_views/{content_hash}-{poses}/{folder}"  # the unlabeled copy of a dataset that methods see
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
    lo, hi = int(pred.min(initial=0)), int(pred.max(initial=0))
    if lo < 0 or hi > 65535:
        raise MethodOutputError(f"method {name!r}, video {video_id} frame {frame_id}: instance ids must lie in "
                                f"[0, 65535], got {lo}..{hi}")
    return pred


def estimated_foreground(video, frame_id: int) -> np.ndarray:
    """bool H×W foreground of ``--foreground plane``: the frame's depth points above the support plane
    (RANSAC with the default :class:`BackgroundConfig`, the methods' own background stage)."""
    from selfseg.baselines.semantic_instances import frame_foreground
    from selfseg.method.background import BackgroundConfig

    return frame_foreground(video, frame_id, BackgroundConfig())


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


# Errors a method's sandbox reports that keep their meaning (one line, exit code 2) in the evaluator.
_INPUT_ERRORS = (DatasetError, FileFormatError, ConfigError, FileNotFoundError, MethodOutputError)


def _sandbox_main(conn, payload: bytes, identities: list[tuple[int, int]], gt_allowed: bool) -> None:
    """A method's process: guard ground truth (unless the method may read it), then import and build the
    method (import-time code runs guarded too) and serve ``fit`` / ``segment`` requests from the parent."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C: the evaluator stops this process
    if not gt_allowed:
        import platform
        from multiprocessing import resource_tracker

        import numpy.testing  # noqa: F401  (libraries start `lscpu` / `uname -p` once: before programs are refused)
        platform.processor()
        resource_tracker.ensure_running()  # process pools need it; it runs no method code
        multiprocessing.set_start_method("fork", force=True)  # Linux's default (a spawned child inherits 'spawn')
        sandbox_ground_truth_guard(identities)
    method = view = None
    while True:
        try:
            request = conn.recv()
        except EOFError:  # the evaluator is gone
            break
        try:
            t0 = time.perf_counter()
            if request[0] == "stop":
                break
            if request[0] == "start":
                method_cls, config, workdir, stage_root, view_root, poses_given = pickle.loads(payload)
                view = Dataset(view_root)
                method = method_cls(config, workdir)
                method.stage_root = stage_root
                open_video = (lambda v: view.labeled(v)) if gt_allowed else (lambda v: view.video(v, poses_given))
                reply = None
            elif request[0] == "fit":
                method.fit([open_video(v) for v in request[1]])
                reply = getattr(method, "train_data", None)  # a method trained on another dataset names it
            else:  # ("segment", video_id, frame_ids, fg masks, staging folder)
                _, vid, frames, fg, staging = request
                preds = method.segment_video(open_video(vid), frames, fg)
                for f in frames:
                    pred = _check_prediction(preds.get(f), method_cls.name, vid, f, (view.height, view.width))
                    write_inst(Path(staging) / PREDICTION_PNG.format(video_id=vid, frame_id=f), pred)
                reply = None
            conn.send(("ok", reply, time.perf_counter() - t0, list(ground_truth_attempts)))
        except BaseException as e:  # noqa: BLE001 (reported to the parent, which raises)
            if isinstance(e, GroundTruthAccessError) and not ground_truth_attempts:  # refused in a forked worker
                ground_truth_attempts.append(str(e))
            try:
                error = pickle.dumps(e) if isinstance(e, _INPUT_ERRORS) else None
            except Exception:  # noqa: BLE001 (an unpicklable error is reported by its traceback)
                error = None
            conn.send(("error", (error, type(e).__name__, traceback.format_exc()), 0.0, list(ground_truth_attempts)))


class MethodSandbox:
    """Runs a method's ``fit`` and ``segment`` in a child process (``spawn``: nothing of the evaluator's
    memory is inherited) that sees only :func:`unlabeled_view` of the dataset, never its path, and
    guards it by identity as a second line. Methods declaring ``needs_ground_truth`` get the labeled
    dataset. One process per fold; ``call("start")`` imports and builds the method, then ``call("fit",
    ids)`` and ``call("segment", ...)``. ``attempts`` lists every refused access, caught by the method or not."""

    def __init__(self, method_cls: type[Method], config, workdir: Path, dataset: Dataset, out: Path,
                 poses_given: bool):
        self.name = method_cls.name
        gt_allowed = method_cls.needs_ground_truth
        self.root = dataset.root if gt_allowed else unlabeled_view(dataset, out, poses_given)
        self._real = dataset.root
        self.attempts: list[str] = []
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        stage_root = (Path(out) / STAGES_DIR).resolve()
        payload = pickle.dumps((method_cls, config, workdir, stage_root, str(self.root.resolve()), poses_given))
        identities = [dataset_identity(dataset.root), dataset_identity(self.root)]
        self._proc = ctx.Process(target=_sandbox_main, args=(child, payload, identities, gt_allowed),
                                 name=f"selfseg-{self.name}")  # not daemonic: it may try to start children
        main_thread = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if main_thread else None
        try:  # the child starts with Ctrl-C ignored (kept across exec): the evaluator alone handles it
            self._proc.start()
        finally:
            if main_thread:
                signal.signal(signal.SIGINT, previous)
        child.close()

    def call(self, *request):
        """Send a request; returns (reply, seconds). Raises the method's error, GroundTruthAccessError first."""
        self._conn.send(request)
        while not self._conn.poll(0.2):
            if not self._proc.is_alive():
                raise RuntimeError(f"method {self.name!r}: its process died (exit code {self._proc.exitcode})")
        status, reply, seconds, self.attempts = self._conn.recv()
        if self.attempts:
            raise GroundTruthAccessError(f"{len(self.attempts)} attempt(s), first: {self.attempts[0]}")
        if status == "error":
            error, kind, tb = reply
            if error is not None:
                error = pickle.loads(error)
                error.args = tuple(a.replace(str(self.root.resolve()), str(self._real)) if isinstance(a, str) else a
                                   for a in error.args)  # name the dataset's files, not the view's
                raise error
            raise RuntimeError(f"method {self.name!r} failed with {kind} in its process:\n{tb}")
        return reply, seconds

    def close(self) -> None:
        if self._proc.is_alive():
            try:
                self._conn.send(("stop",))
            except OSError:
                pass
            self._proc.join(5)
            if self._proc.is_alive():
                self._proc.kill()
                self._proc.join()
        self._conn.close()


def results_key(out: Path, dataset: Dataset) -> str:
    """The folder name a dataset's results are filed under in ``out``: its name, or ``<name>-<content hash>``
    when ``scores/<name>/`` already holds results of a different dataset with the same name."""
    content = dataset.content_hash()
    for path in sorted((Path(out) / "scores" / dataset.name).glob("*/fold*.json")):
        if read_json(path).get("dataset", {}).get("content_hash") != content:
            return f"{dataset.name}-{content[:8]}"
    return dataset.name


def _resume_key(record: dict) -> dict:
    options = {k: v for k, v in record["options"].items() if k != "folds"}
    return {"method": record["method"], "config_hash": record["config_hash"], "options": options,
            "dataset": record["dataset"]["content_hash"], "commit": record["git"]["commit"]}


def finished_fold(method_cls: type[Method], config, dataset: Dataset, fold: int, out: Path,
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


def run_fold(method_cls: type[Method], config, dataset: Dataset, fold: int, out: Path,
             options: EvalOptions = EvalOptions(), progress: bool = True) -> dict:
    """Fit, segment, write and score one fold; writes the result JSON and frame sidecar; returns the record.

    The method runs in a :class:`MethodSandbox`; if it reached for ground truth, a record with
    ``ground_truth_attempts`` is written to ``REJECTED_JSON`` (nothing is scored) and
    :class:`GroundTruthAccessError` is raised. Predictions are written to a staging folder and
    replace each test video's folder only once the fold is complete (no stale frames remain)."""
    out = Path(out)
    name = options.name or method_cls.name
    key = results_key(out, dataset)
    fmt = {"dataset": key, "name": name, "fold": fold}
    train_ids, test_ids = fold_split(dataset, fold)
    workdir = out / WORK_DIR.format(**fmt)
    workdir.mkdir(parents=True, exist_ok=True)
    pred_dir = out / PREDICTIONS_DIR.format(**fmt)
    staging = pred_dir.parent / f".{pred_dir.name}.fold{fold}.partial"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)

    seg_s = 0.0
    n_frames = 0
    written: list[tuple[str, int]] = []
    gts: dict[tuple[str, int], np.ndarray] = {}
    sandbox = MethodSandbox(method_cls, config, workdir.resolve(), dataset, out, options.poses_given)
    try:
        sandbox.call("start")  # imports and builds the method, in its process
        train_data, fit_s = sandbox.call("fit", train_ids)
        for vid in tqdm(test_ids, desc=f"{name} fold {fold}: segment", unit="video", disable=not progress):
            labeled = dataset.labeled(vid)
            frames = select_test_frames(labeled.frame_ids, options.frame_stride, options.limit)
            fg = {}
            for f in frames:
                gts[vid, f] = labeled.inst(f)
                fg[f] = gts[vid, f] > 0 if options.foreground == "gt" else estimated_foreground(labeled, f)
            _, seconds = sandbox.call("segment", vid, frames, fg, str(staging.resolve()))
            seg_s += seconds
            n_frames += len(frames)
            written += [(vid, f) for f in frames]
    except GroundTruthAccessError as e:
        write_json(out / REJECTED_JSON.format(**fmt), {
            **provenance(method_cls.name, name, config, dataset, "2d"), "fold": fold,
            "options": dataclasses.asdict(options), "ground_truth_attempts": sandbox.attempts})
        shutil.rmtree(staging, ignore_errors=True)
        raise GroundTruthAccessError(f"method {name!r}, fold {fold}: {e}") from None
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    finally:
        sandbox.close()

    evaluator = SegmentationEvaluator(n_boot=options.n_boot, seed=options.seed)
    t0 = time.perf_counter()
    for vid, f in tqdm(written, desc=f"{name} fold {fold}: score", unit="frame", disable=not progress):
        evaluator.process(vid, f, read_inst(staging / PREDICTION_PNG.format(video_id=vid, frame_id=f)), gts[vid, f])
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
        "ground_truth_attempts": [],
    }
    record["dataset"]["key"] = key
    if train_data:  # hook: a method trained on another dataset names it (a dict) in fit
        record["train_data"] = train_data
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
    fmt = {"dataset": record["dataset"].get("key", record["dataset"]["name"]), "name": record["name"],
           "fold": record["fold"]}
    path = Path(out) / SCORES_JSON.format(**fmt)
    write_json(path, record)
    atomic_write_text(Path(out) / FRAMES_JSONL.format(**fmt), "".join(dumps_json(f, indent=None) + "\n" for f in frames))
    return path
