"""Saved models: what ``train`` writes and ``segment`` reads (the commands: :mod:`selfseg.method.cli`).

:func:`train_model` runs the method's ``fit`` on every video of the dataset (or the given ones), no
folds, inside the ground-truth guard, and writes the model folder atomically: ``weights.pt`` (the
network), ``config.json`` (the method's resolved config, clustering settings included) and
``model.json`` (model format version, method, config hash, selfseg/torch versions, the training
data's content hash and videos). The method's caches go to ``MODEL_DIR.work/`` (a re-run reuses
them; resumable), and what libraries print while it fits (Open3D's registration warnings) to
``MODEL_DIR.work/library.log`` (:mod:`selfseg.library_log`), counted in one line at the end.

:func:`run_segment` loads the model and segments like the method does in ``evaluate``: the network
embeds the frame (at its training scale, inside the foreground box when trained with ``fg_crop``)
and vMF mean-shift clusters the foreground pixels. The foreground is a mask PNG (non-zero =
foreground), ``plane`` (:func:`selfseg.method.background.frame_foreground` with the method's
``background`` settings: depth back-projected with K, the dominant support plane removed by RANSAC),
or every pixel when not given. The output is a uint16 instance PNG (0 = background); ``--preview``
adds a colour overlay PNG (``<out>.preview.png``, or ``OUT_DIR/preview/``). In folder mode files are
paired by stem, a progress bar runs and the measured frames per second are printed. Depth PNGs:
uint16, mm = value × ``--depth-scale``.
"""
from __future__ import annotations

import argparse
import pickle
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from selfseg.config import ConfigError, config_hash, from_dict, load_config, to_dict
from selfseg.dataset import Dataset, DatasetError, read_depth_m, read_inst, read_rgb, validate_K
from selfseg.fileio import atomic_dir, read_json, write_json
from selfseg.guard import ground_truth_forbidden
from selfseg.importers import IMAGE_EXTS, image_files, read_intrinsics
from selfseg.library_log import run_log, summary
from selfseg.method.background import frame_foreground
from selfseg.method.features import input_frame
from selfseg.method.pipeline import Ours
from selfseg.registry import UnknownMethodError, get_method_class
from selfseg.writers import write_inst, write_rgb

MODEL_FORMAT = "selfseg-model"
MODEL_VERSION = 1
MODEL_JSON, CONFIG_JSON, WEIGHTS_PT = "model.json", "config.json", "weights.pt"


class ModelError(ValueError):
    """A model folder that cannot be used; the message names the file and the problem."""


def _embedding_method(name: str):
    cls = get_method_class(name)
    if not issubclass(cls, Ours):
        raise ConfigError(f"--method {name!r}: train/segment support the unlabeled embedding methods "
                          "(ours, ours-v2, ours-v3, ours-v4)")
    return cls


def _versions() -> dict:
    import importlib.metadata

    return {p: importlib.metadata.version(p) for p in ("selfseg", "torch", "numpy")}


def train_model(method: str, data: Path, out: Path, config_path: Path | None = None, overrides: list[str] = (),
                videos: list[str] | None = None) -> Path:
    """Fit ``method`` on the dataset's videos (unlabeled) and save the model folder ``out``; returns it."""
    cls = _embedding_method(method)
    config = load_config(cls.config_cls, config_path, overrides)
    dataset = Dataset(data)
    ids = videos or dataset.video_ids
    for v in ids:
        dataset.video(v)  # unknown ids: one clear error
    if (out / MODEL_JSON).is_file():
        raise FileExistsError(f"{out}: a model already exists; choose another --out or delete it")
    m = cls(config, Path(f"{out}.work") / "train" / dataset.name / "all")
    m.stage_root = Path(f"{out}.work") / "_stages"  # per-video stages: <out>.work/_stages/<dataset folder>-<hash>
    with ground_truth_forbidden(dataset.root), run_log(Path(f"{out}.work") / "library.log") as log:
        m.fit([dataset.video(v) for v in ids])
    logged = summary(log)
    if logged:
        print(f"train: {logged}", file=sys.stderr)
    with atomic_dir(out) as tmp:
        shutil.copyfile(m.weights_path, tmp / WEIGHTS_PT)
        write_json(tmp / CONFIG_JSON, to_dict(config))
        write_json(tmp / MODEL_JSON, {
            "format": MODEL_FORMAT, "model_version": MODEL_VERSION, "method": cls.name,
            "config_hash": config_hash(config), "cluster": to_dict(config.cluster), "versions": _versions(),
            "training_data": {"name": dataset.name, "root": str(dataset.root.resolve()),
                              "content_hash": dataset.content_hash(), "videos": ids,
                              "n_frames": sum(len(dataset.video(v)) for v in ids)}})
    return out


def load_model(model_dir: Path):
    """The method instance saved in ``model_dir``, with its network loaded (for :func:`segment_frame`)."""
    meta_path = Path(model_dir) / MODEL_JSON
    if not meta_path.is_file():
        raise ModelError(f"{meta_path}: missing; {model_dir} is not a model folder written by train")
    meta = read_json(meta_path)
    if not isinstance(meta, dict):
        raise ModelError(f"{meta_path}: expected a JSON object, got a {type(meta).__name__}")
    if meta.get("format") != MODEL_FORMAT or meta.get("model_version") != MODEL_VERSION:
        raise ModelError(f"{meta_path}: model format {meta.get('format')!r} version {meta.get('model_version')!r}, "
                         f"this selfseg reads {MODEL_FORMAT} version {MODEL_VERSION}")
    try:
        cls = _embedding_method(str(meta.get("method")))
    except (UnknownMethodError, ConfigError) as e:
        raise ModelError(f"{meta_path}: method {meta.get('method')!r} cannot segment here ({e})") from None
    try:
        config = from_dict(cls.config_cls, read_json(Path(model_dir) / CONFIG_JSON))
    except (ConfigError, TypeError, AttributeError) as e:  # not a mapping of the config's fields
        raise ModelError(f"{Path(model_dir) / CONFIG_JSON}: not a {cls.name} config ({e})") from None
    if config_hash(config) != meta.get("config_hash"):
        raise ModelError(f"{Path(model_dir) / CONFIG_JSON}: config hash {config_hash(config)} differs from "
                         f"model.json's {meta.get('config_hash')}")
    m = cls(config, None)
    try:
        m.load(Path(model_dir) / WEIGHTS_PT)
    except (pickle.UnpicklingError, EOFError) as e:  # not a file torch.save wrote (zero bytes, an image, text)
        raise ModelError(f"{Path(model_dir) / WEIGHTS_PT}: not a weights file written by train "
                         f"({str(e).splitlines()[0] if str(e) else type(e).__name__})") from None
    except (RuntimeError, KeyError, TypeError, ValueError, AttributeError, IndexError) as e:
        raise ModelError(f"{Path(model_dir) / WEIGHTS_PT}: weights do not fit the {cls.name} network "
                         f"({str(e).splitlines()[0] if str(e) else type(e).__name__})") from None
    return m


def segment_frame(method, rgb: np.ndarray, fg_mask: np.ndarray, depth_m: np.ndarray | None = None,
                  K: np.ndarray | None = None) -> np.ndarray:
    """uint16 H×W instance map of one frame, as ``method.segment`` computes it in ``evaluate`` (on a GPU too); a
    network with geometry input needs the frame's depth (m) and ``K``."""
    geometry = method.config.net.geometry
    if geometry and (depth_m is None or K is None):
        raise ConfigError(f"model of {method.name!r} reads depth and normals: pass --depth and --intrinsics")
    return method.segment_frame(input_frame(rgb, depth_m, K, geometry), fg_mask).astype(np.uint16)


def preview(rgb: np.ndarray, inst: np.ndarray) -> np.ndarray:
    """uint8 H×W×3: the frame with each instance tinted by a fixed colour (id-seeded) and a dark boundary."""
    import cv2

    ids = np.unique(inst[inst > 0])
    colours = np.zeros((int(inst.max()) + 1, 3), np.float32)
    for i in ids:
        colours[i] = np.random.default_rng(int(i)).integers(40, 256, 3)
    out = rgb.astype(np.float32)
    m = inst > 0
    out[m] = 0.45 * out[m] + 0.55 * colours[inst[m]]
    edge = cv2.morphologyEx(inst.astype(np.float32), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
    out[edge & m] = 0
    return out.astype(np.uint8)


def _write_preview(path: Path, rgb: np.ndarray, inst: np.ndarray) -> None:
    write_rgb(path, preview(rgb, inst))


def _foreground(spec: str | None, fg_path: Path | None, rgb: np.ndarray, depth: np.ndarray | None,
                K: np.ndarray | None, method, name: str) -> np.ndarray:
    if spec == "plane":
        return frame_foreground(depth, K, method.config.background, f"video {name} frame 0")
    if fg_path is not None:
        m = read_inst(fg_path) > 0
        if m.shape != rgb.shape[:2]:
            raise DatasetError(f"{fg_path}: mask is {m.shape[1]}×{m.shape[0]}, colour is {rgb.shape[1]}×{rgb.shape[0]}")
        return m
    return np.ones(rgb.shape[:2], bool)


def run_segment(args: argparse.Namespace) -> int:
    """The ``segment`` command on parsed arguments (see :func:`selfseg.method.cli.segment_parser`)."""
    method = load_model(args.model)
    plane = args.foreground == "plane"
    if plane and (args.depth is None or args.intrinsics is None):
        raise ConfigError("--foreground plane needs --depth and --intrinsics")
    K = read_intrinsics(args.intrinsics) if args.intrinsics else None
    folder = args.rgb.is_dir()
    if folder:
        rgbs = image_files(args.rgb)
        if not rgbs:
            raise DatasetError(f"{args.rgb}: no {'/'.join(IMAGE_EXTS)} frames")
        depths = image_files(args.depth) if args.depth else {}
        fgs = image_files(Path(args.foreground)) if args.foreground and not plane else {}
        for what, d, src in (("depth", depths, args.depth), ("foreground", fgs, args.foreground)):
            if src is not None and not (what == "foreground" and plane):
                miss = [s for s in rgbs if s not in d]
                if miss:
                    raise DatasetError(f"{src}: no {what} frame for {rgbs[miss[0]].name} ({len(miss)} missing)")
        jobs = [(s, rgbs[s], depths.get(s), fgs.get(s), args.out / f"{s}.png") for s in rgbs]
    else:
        jobs = [(args.rgb.stem, args.rgb, args.depth, None if plane or not args.foreground else Path(args.foreground),
                 args.out)]
    t0, n = time.perf_counter(), 0
    for stem, rgb_p, depth_p, fg_p, out_p in tqdm(jobs, desc="segment", unit="frame", disable=args.quiet or not folder):
        rgb = read_rgb(rgb_p)
        depth = None
        if depth_p is not None:
            depth = read_depth_m(depth_p, args.depth_scale)
            if depth.shape != rgb.shape[:2]:
                raise DatasetError(f"{depth_p}: depth is {depth.shape[1]}×{depth.shape[0]}, colour is "
                                   f"{rgb.shape[1]}×{rgb.shape[0]}")
        if K is not None:
            validate_K(K, rgb.shape[1], rgb.shape[0], str(args.intrinsics))
        fg = _foreground(args.foreground, fg_p, rgb, depth, K, method, stem)
        inst = segment_frame(method, rgb, fg, depth, K)
        write_inst(out_p, inst)
        if args.preview:
            _write_preview(out_p.parent / "preview" / out_p.name if folder else out_p.with_suffix(".preview.png"),
                           rgb, inst)
        n += 1
    dt = time.perf_counter() - t0
    print(f"segment: {n} frame{'s' * (n != 1)} in {dt:.2f} s = {n / dt:.2f} fps (I/O and foreground included) "
          f"→ {args.out}")
    return 0
