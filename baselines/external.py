"""Score predictions made elsewhere (UOIS, SD-MaskRCNN, STEGO, ...) from a folder of PNGs.

Layout, like a video's ``mask_inst/``::

    PREDICTIONS/<video_id>/<frame_id:06d>.png    uint16 (or uint8) single-channel, W×H of the
                                                 dataset; 0 = no object, other ids arbitrary

Only the evaluated test frames need to exist. The harness's own prediction folder
``OUT/predictions/<name>/<dataset>/`` has this layout, so any run can be re-scored from disk.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from selfseg.dataset import DatasetError, Video, read_inst
from selfseg.eval.layout import PREDICTION_PNG
from selfseg.method_api import Method


class PredictionsError(DatasetError):
    """A predictions folder is missing, or holds a missing or malformed frame (the message names the file)."""


@dataclass
class ExternalConfig:
    predictions: str = ""  # folder laid out as PREDICTIONS/<video_id>/<frame_id:06d>.png


def prediction_path(root: str | Path, video_id: str, frame_id: int) -> Path:
    return Path(root) / PREDICTION_PNG.format(video_id=video_id, frame_id=frame_id)


def read_prediction(root: str | Path, video_id: str, frame_id: int, width: int, height: int) -> np.ndarray:
    """One predicted instance map (uint16 H×W), with errors naming the file."""
    path = prediction_path(root, video_id, frame_id)
    if not path.is_file():
        raise PredictionsError(f"{path}: missing prediction for video {video_id} frame {frame_id}")
    try:
        pred = read_inst(path)
    except DatasetError as e:
        raise PredictionsError(str(e)) from None
    if pred.shape != (height, width):
        raise PredictionsError(f"{path}: prediction is {pred.shape[1]}×{pred.shape[0]}, expected {width}×{height}")
    return pred


class ExternalPredictions(Method):
    """Reads the predictions of a method run elsewhere (config ``predictions``, CLI ``--predictions``)."""

    name = "external"
    config_cls = ExternalConfig

    def __init__(self, config=None, workdir=None):
        super().__init__(config, workdir)
        root = Path(self.config.predictions) if self.config.predictions else None
        if root is None or not root.is_dir():
            raise PredictionsError(f"{root or '(none)'}: predictions folder not found "
                                   "(the external method needs --predictions DIR)")
        self.root = root

    def segment(self, video: Video, frame_id: int, fg_mask: np.ndarray) -> np.ndarray:
        return read_prediction(self.root, video.video_id, frame_id, video.width, video.height)
