"""The method stage's commands, ``train`` and ``segment``: parsers and thin mains over :mod:`selfseg.method.deploy`.

    train --method ours --data DIR [--config FILE] [--set key=value ...] [--videos ID,ID] --out MODEL_DIR
    segment --model MODEL_DIR --rgb X.png [--depth Y.png --intrinsics K.txt] [--depth-scale MM]
            [--foreground mask.png | --foreground plane] --out OUT.png [--preview]
    segment --model MODEL_DIR --rgb RGB_DIR [--depth DEPTH_DIR --intrinsics K.txt]
            [--foreground MASK_DIR | --foreground plane] --out OUT_DIR [--preview]

Bad input prints one line naming the file and the problem and exits with status 2.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from selfseg.config import ConfigError
from selfseg.dataset import DatasetError
from selfseg.fileio import FileFormatError
from selfseg.guard import GroundTruthAccessError
from selfseg.method.deploy import ModelError, run_segment, train_model
from selfseg.registry import UnknownMethodError


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

