"""What a fold's method process sees: the unlabeled view of the dataset (:func:`unlabeled_view`), its stage root
(:func:`method_stage_root`) and the whole mount plan of its sandbox (:func:`fold_mounts`)."""
from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from selfseg.config import to_dict
from selfseg.dataset import DATASET_INFO, DEPTH, RGB, SCENE_CAMERA, VIDEO_DIR, Dataset, DatasetError
from selfseg.eval.folds import EvalOptions
from selfseg.eval.layout import LABELED_STAGE_ROOT_DIR, LIBRARY_LOG, STAGE_ROOT_DIR, VIEW_DIR, WORK_DIR, results_key
from selfseg.eval.sandbox import MethodRef, Mount, check_mounts
from selfseg.fileio import atomic_dir, read_json, write_json
from selfseg.guard import guard_paths


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


@dataclass
class FoldMounts:
    """A fold's method process as :func:`fold_mounts` plans it (paths as that process sees them)."""

    mounts: list[Mount]  # its sandbox's mounts besides the system, the environment and the method's own code
    root: Path  # the dataset folder it reads
    workdir: Path  # its work folder (``Method.workdir``)
    log: Path  # its library log (selfseg.library_log), in its work folder
    stage_root: Path | None  # a registered method's stage root (``Method.stage_root``); a user's method: None
    config: dict | None  # its config (None: its defaults)
    labeled: tuple[bool, bool]  # whether the training videos, the test videos are opened with their labels
    guard: list[str]  # the paths the in-process check (selfseg.guard) refuses there


def fold_mounts(ref: MethodRef, config, dataset: Dataset, view: Path, fold: int, out: Path, options: EvalOptions,
                train_ids: list[str], test_ids: list[str], output: Path) -> FoldMounts:
    """What a fold's method process is given (``ground truth``: the labels granted, see
    :data:`selfseg.eval.sandbox.GROUND_TRUTH`):

    * the dataset as ``view`` (:func:`unlabeled_view`) at the view's path: ``dataset_info.json`` and every video's folder,
      read-only; the training videos' folders (labels included) from the dataset itself when labels are
      granted, the test videos' too only for "all" (the oracle);
    * its work folder, writable: the run's ``work/<name>/<dataset>/`` (its folds share it) when it is given no
      labels, else only the fold's (no fold sees labels another fold was given, which include its test videos');
      the fold's library log lies in it (``LIBRARY_LOG``);
    * a registered method: its stage root (:func:`method_stage_root`, writable) and the folders its config names
      (``registry.CONFIG_DIRS``); a user's method: no stage root (it caches in its work folder);
    * ``output``, writable, for its predictions.

    Unsandboxed, the same paths are given to a plain child process; it reads the real dataset when given labels.
    The folders are created here; a mount that would hold the dataset or lie inside it is refused (SandboxError)."""
    granted = "train" if options.method_needs_ground_truth else ref.ground_truth
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
    return FoldMounts(mounts, root, workdir, (out / LIBRARY_LOG.format(**fmt)).resolve(), stage_root, config_dict,
                      (granted != "none", granted == "all"), guard)
