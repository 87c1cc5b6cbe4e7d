"""Scoring a fold: the predictions a method's process wrote, checked there (:func:`check_prediction`), read back by
the evaluator only as plain files (:func:`read_prediction`) and scored against the ground truth
(:func:`score_fold`)."""
from __future__ import annotations

import os
import stat
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from selfseg.dataset import read_inst
from selfseg.eval.aggregate import SegmentationEvaluator
from selfseg.eval.folds import EvalOptions
from selfseg.eval.layout import PREDICTION_PNG
from selfseg.writers import write_inst


class MethodOutputError(ValueError):
    """A method returned something that is not a valid instance map for a requested frame."""


def check_prediction(pred, name: str, video_id: str, frame_id: int, shape: tuple[int, int]) -> np.ndarray:
    """In the method's process: the instance map method ``name`` returned for a frame, as an array, if it is one
    (integer, ``shape``, ids in [0, 65535]); else MethodOutputError."""
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


def read_prediction(output: Path, name: str, video_id: str, frame_id: int, shape: tuple[int, int]) -> np.ndarray:
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


def score_fold(output: Path, method: str, label: str, test_frames: dict[str, list[int]],
               gts: dict[tuple[str, int], np.ndarray], shape: tuple[int, int], staging: Path, options: EvalOptions,
               progress: bool) -> tuple[SegmentationEvaluator, float]:
    """Score every test frame's prediction in ``output`` (method ``method``'s, :func:`read_prediction`) against its
    ground truth ``gts[video, frame]`` and write it to ``staging``; returns the evaluator and the seconds scoring
    took. ``label`` ("<name> fold <k>") names the progress bars."""
    evaluator = SegmentationEvaluator(n_boot=options.n_boot, seed=options.seed)
    score_s = 0.0
    for vid, frames in test_frames.items():
        for f in tqdm(frames, desc=f"{label}: score {vid}", unit="frame", disable=not progress):
            t0 = time.perf_counter()
            pred = read_prediction(output, method, vid, f, shape)
            evaluator.process(vid, f, pred, gts[vid, f])
            score_s += time.perf_counter() - t0
            write_inst(staging / PREDICTION_PNG.format(video_id=vid, frame_id=f), pred)
    return evaluator, score_s
