"""``train`` and ``segment``: train a method on unlabeled recordings, keep the model, segment new frames.

    train --method ours --data DIR [--config FILE] [--set key=value ...] [--videos ID,ID] --out MODEL_DIR
    segment --model MODEL_DIR --rgb X.png [--depth Y.png --intrinsics K.txt] [--depth-scale MM]
            [--foreground mask.png | --foreground plane] --out OUT.png [--preview]
    segment --model MODEL_DIR --rgb RGB_DIR [--depth DEPTH_DIR --intrinsics K.txt]
            [--foreground MASK_DIR | --foreground plane] --out OUT_DIR [--preview]

``train`` runs the method's ``fit`` on every video of the dataset (or ``--videos``), no folds, inside
the ground-truth guard, and writes ``MODEL_DIR`` atomically: ``weights.pt`` (the network),
``config.json`` (the method's resolved config, clustering settings included) and ``model.json``
(model format version, method, config hash, selfseg/torch versions, the training data's content hash
and videos). The method's caches go to ``MODEL_DIR.work/`` (a re-run reuses them; resumable).

``segment`` loads the model and segments like the method does in ``evaluate``: the network embeds the
frame (at its training scale, inside the foreground box when trained with ``fg_crop``) and vMF
mean-shift clusters the foreground pixels. The foreground is a mask PNG (non-zero = foreground),
``plane`` (depth back-projected with K, the dominant support plane removed by RANSAC with the
method's ``background`` settings, :func:`selfseg.baselines.semantic_instances.frame_foreground`,
i.e. :func:`selfseg.method.background.remove_support_plane`), or every pixel when not given. The
output is a uint16 instance PNG (0 = background); ``--preview`` adds a colour overlay PNG
(``<out>.preview.png``, or ``OUT_DIR/preview/``). In folder mode files are paired by stem, a progress
bar runs and the measured frames per second are printed. Depth PNGs: uint16, mm = value × ``--depth-scale``.
Bad input prints one line naming the file and the problem and exits with status 2.
"""
from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from selfseg.config import ConfigError, config_hash, from_dict, load_config, to_dict
from selfseg.dataset import Dataset, DatasetError, read_depth_m, read_inst, read_rgb, validate_K, write_inst
from selfseg.fileio import FileFormatError, atomic_dir, read_json, write_json
from selfseg.guard import GroundTruthAccessError, ground_truth_forbidden
from selfseg.registry import UnknownMethodError, get_method_class

MODEL_FORMAT = "selfseg-model"
MODEL_VERSION = 1
MODEL_JSON, CONFIG_JSON, WEIGHTS_PT = "model.json", "config.json", "weights.pt"


class ModelError(ValueError):
    """A model folder that cannot be used; the message names the file and the problem."""


def _embedding_method(name: str):
    from selfseg.method.pipeline import Ours

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
    with ground_truth_forbidden(dataset.root):
        m.fit([dataset.video(v) for v in ids])
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
    if meta.get("format") != MODEL_FORMAT or meta.get("model_version") != MODEL_VERSION:
        raise ModelError(f"{meta_path}: model format {meta.get('format')!r} version {meta.get('model_version')!r}, "
                         f"this selfseg reads {MODEL_FORMAT} version {MODEL_VERSION}")
    try:
        cls = _embedding_method(str(meta.get("method")))
    except (UnknownMethodError, ConfigError) as e:
        raise ModelError(f"{meta_path}: method {meta.get('method')!r} cannot segment here ({e})") from None
    try:
        config = from_dict(cls.config_cls, read_json(Path(model_dir) / CONFIG_JSON))
    except ConfigError as e:
        raise ModelError(f"{Path(model_dir) / CONFIG_JSON}: not a {cls.name} config ({e})") from None
    if config_hash(config) != meta.get("config_hash"):
        raise ModelError(f"{Path(model_dir) / CONFIG_JSON}: config hash {config_hash(config)} differs from "
                         f"model.json's {meta.get('config_hash')}")
    m = cls(config, None)
    try:
        m.load(Path(model_dir) / WEIGHTS_PT)
    except (RuntimeError, KeyError) as e:
        raise ModelError(f"{Path(model_dir) / WEIGHTS_PT}: weights do not fit the {cls.name} network ({e})") from None
    return m


class _Frame:
    """The one frame a foreground estimator needs: depth in metres and K (a :class:`Video`'s accessors)."""

    def __init__(self, depth_m: np.ndarray, K: np.ndarray, name: str):
        self._depth, self._K, self.video_id = depth_m, K, name

    def depth_m(self, frame_id: int) -> np.ndarray:
        return self._depth

    def K(self, frame_id: int | None = None) -> np.ndarray:
        return self._K


def plane_foreground(depth_m: np.ndarray, K: np.ndarray, bg_cfg, name: str = "frame") -> np.ndarray:
    """bool H×W: pixels whose depth point stands above the dominant support plane (the methods' RANSAC)."""
    from selfseg.baselines.semantic_instances import frame_foreground

    return frame_foreground(_Frame(depth_m, K, name), 0, bg_cfg)


def segment_frame(method, rgb: np.ndarray, fg_mask: np.ndarray) -> np.ndarray:
    """uint16 H×W instance map of one frame, as ``method.segment`` computes it in ``evaluate``."""
    from selfseg.method.meanshift import cluster_frame

    return cluster_frame(method.embed(rgb, fg_mask), fg_mask, method.config.cluster).astype(np.uint16)


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
    from selfseg.dataset import write_rgb

    write_rgb(path, preview(rgb, inst))


def _foreground(spec: str | None, fg_path: Path | None, rgb: np.ndarray, depth: np.ndarray | None,
                K: np.ndarray | None, method, name: str) -> np.ndarray:
    if spec == "plane":
        return plane_foreground(depth, K, method.config.background, name)
    if fg_path is not None:
        m = read_inst(fg_path) > 0
        if m.shape != rgb.shape[:2]:
            raise DatasetError(f"{fg_path}: mask is {m.shape[1]}×{m.shape[0]}, colour is {rgb.shape[1]}×{rgb.shape[0]}")
        return m
    return np.ones(rgb.shape[:2], bool)


def run_segment(args: argparse.Namespace) -> int:
    from selfseg.importers import IMAGE_EXTS, _images, read_intrinsics

    method = load_model(args.model)
    plane = args.foreground == "plane"
    if plane and (args.depth is None or args.intrinsics is None):
        raise ConfigError("--foreground plane needs --depth and --intrinsics")
    K = read_intrinsics(args.intrinsics) if args.intrinsics else None
    folder = args.rgb.is_dir()
    if folder:
        rgbs = _images(args.rgb)
        if not rgbs:
            raise DatasetError(f"{args.rgb}: no {'/'.join(IMAGE_EXTS)} frames")
        depths = _images(args.depth) if args.depth else {}
        fgs = _images(Path(args.foreground)) if args.foreground and not plane else {}
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
        inst = segment_frame(method, rgb, fg)
        write_inst(out_p, inst)
        if args.preview:
            _write_preview(out_p.parent / "preview" / out_p.name if folder else out_p.with_suffix(".preview.png"),
                           rgb, inst)
        n += 1
    dt = time.perf_counter() - t0
    print(f"segment: {n} frame{'s' * (n != 1)} in {dt:.2f} s = {n / dt:.2f} fps (I/O and foreground included) "
          f"→ {args.out}")
    return 0


def train_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="train", description="Train an unlabeled method on every video of a dataset "
                                "(no folds) and save the model for segment.")
    p.add_argument("--method", required=True, help="ours, ours-v2, ours-v3 or ours-v4")
    p.add_argument("--data", required=True, type=Path, help="dataset folder (labels not needed, never read)")
    p.add_argument("--config", type=Path, help="YAML file with the method's config (as in evaluate)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value (repeatable), as in evaluate")
    p.add_argument("--videos", help="comma-separated video ids to train on (default: all)")
    p.add_argument("--out", required=True, type=Path, help="model folder to write")
    return p


def segment_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="segment", description="Segment frames with a model saved by train.")
    p.add_argument("--model", required=True, type=Path, help="model folder written by train")
    p.add_argument("--rgb", required=True, type=Path, help="colour image, or a folder of them (folder mode)")
    p.add_argument("--depth", type=Path, help="uint16 depth PNG (or folder), mm = value × --depth-scale")
    p.add_argument("--depth-scale", type=float, default=1.0, help="millimetres per depth unit (default 1)")
    p.add_argument("--intrinsics", type=Path, help="file with 'fx fy cx cy' (pixel-centre convention) or a 3×3 K")
    p.add_argument("--foreground", help="mask PNG (or folder; non-zero = foreground) or 'plane' (default: all pixels)")
    p.add_argument("--out", required=True, type=Path, help="output instance PNG, or folder in folder mode")
    p.add_argument("--preview", action="store_true", help="also write a colour overlay PNG")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _main(prog: str, fn, argv) -> int:
    try:
        return fn(argv)
    except GroundTruthAccessError as e:
        print(f"{prog}: error: the method tried to read ground truth: {e}", file=sys.stderr)
    except (UnknownMethodError, ConfigError, DatasetError, FileFormatError, FileNotFoundError, FileExistsError,
            ModelError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
    return 2


def _train(argv) -> int:
    a = train_parser().parse_args(argv)
    videos = [v.strip() for v in a.videos.split(",") if v.strip()] if a.videos else None
    out = train_model(a.method, a.data, a.out, a.config, a.overrides, videos)
    print(f"train: model written to {out}")
    return 0


def train_main(argv: list[str] | None = None) -> int:
    return _main("train", _train, argv)


def segment_main(argv: list[str] | None = None) -> int:
    return _main("segment", lambda argv: run_segment(segment_parser().parse_args(argv)), argv)

