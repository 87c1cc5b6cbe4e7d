"""Writers of the dataset format (:mod:`selfseg.dataset`): images, camera and ground-truth records,
``dataset_info.json`` and whole video folders. Every file is written atomically."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from selfseg.dataset import (CAMERA_JSON, DATASET_INFO, DEPTH_SCALE_MM, FORMAT_VERSION, FRAME_DEPTH, FRAME_MASK_INST,
                             FRAME_RGB, GT_JSON, INFO_JSON, DatasetError)
from selfseg.fileio import atomic_write_bytes, write_json
from selfseg.poses import T_to_rt, invert_T


# ---- images ----------------------------------------------------------------------------------
def _encode_png(path: Path, img: np.ndarray) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise DatasetError(f"{path}: PNG encoding failed")
    atomic_write_bytes(path, buf.tobytes())


def write_rgb(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """uint8 H×W×3 RGB → 8-bit PNG (atomic)."""
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"{path}: rgb must be uint8 H×W×3, got {rgb.dtype} {rgb.shape}")
    _encode_png(Path(path), np.ascontiguousarray(rgb[:, :, ::-1]))


def depth_to_png_units(depth_m: np.ndarray, depth_scale: float = DEPTH_SCALE_MM) -> np.ndarray:
    """Quantise metres to uint16 PNG units (round to nearest); 0 and inf become 0 (no measurement).

    NaN is refused: a renderer or sensor must say explicitly which pixels have no depth.
    """
    d = np.asarray(depth_m, dtype=np.float64)
    if np.isnan(d).any():
        raise ValueError(f"depth contains {int(np.isnan(d).sum())} NaN values; use 0 for 'no measurement'")
    units = np.where(np.isfinite(d) & (d > 0), np.rint(d * 1000.0 / depth_scale), 0.0)
    if units.max(initial=0) > 65535:
        raise ValueError(f"depth {d[np.isfinite(d)].max():.3f} m exceeds the uint16 range at depth_scale={depth_scale}")
    return units.astype(np.uint16)


def write_depth_m(path: str | os.PathLike, depth_m: np.ndarray, depth_scale: float = DEPTH_SCALE_MM) -> None:
    """float metres → uint16 PNG with mm = value * depth_scale (atomic)."""
    _encode_png(Path(path), depth_to_png_units(depth_m, depth_scale))


def write_inst(path: str | os.PathLike, inst: np.ndarray) -> None:
    """Integer instance map (0 = background) → uint16 PNG (atomic)."""
    inst = np.asarray(inst)
    if inst.ndim != 2 or not np.issubdtype(inst.dtype, np.integer) or inst.min(initial=0) < 0 or inst.max(initial=0) > 65535:
        raise ValueError(f"{path}: instance map must be a 2-D array of ids in [0, 65535], got {inst.dtype} {inst.shape}")
    _encode_png(Path(path), inst.astype(np.uint16))


# ---- records and folders --------------------------------------------------------------------
def camera_record(K: np.ndarray, T_world_cam: np.ndarray, depth_scale: float = DEPTH_SCALE_MM) -> dict:
    """One scene_camera.json entry."""
    R, t = T_to_rt(invert_T(T_world_cam))
    return {"cam_K": np.asarray(K, dtype=np.float64).reshape(-1).tolist(), "depth_scale": float(depth_scale),
            "cam_R_w2c": R, "cam_t_w2c": t}


def gt_record(obj_id: int, inst_id: int, T_cam_model: np.ndarray) -> dict:
    """One scene_gt.json entry."""
    R, t = T_to_rt(T_cam_model)
    return {"obj_id": int(obj_id), "inst_id": int(inst_id), "cam_R_m2c": R, "cam_t_m2c": t}


def write_dataset_info(root: str | os.PathLike, info: dict) -> None:
    """Write dataset_info.json, stamping the format version."""
    write_json(Path(root) / DATASET_INFO, {**info, "format_version": FORMAT_VERSION})


class VideoWriter:
    """Writes one video folder in the dataset format (frames first, then the JSON records)."""

    def __init__(self, video_dir: str | os.PathLike):
        self.dir = Path(video_dir)
        self.cameras: dict[str, dict] = {}
        self.gts: dict[str, list] = {}

    def _frame(self, template: str, frame_id: int) -> Path:
        return self.dir / template.format(frame_id=frame_id)

    def write_frame(self, frame_id: int, rgb: np.ndarray, depth_m: np.ndarray, inst: np.ndarray | None,
                    K: np.ndarray, T_world_cam: np.ndarray, objects: list[dict] | None,
                    depth_scale: float = DEPTH_SCALE_MM) -> None:
        """objects: [{obj_id, inst_id, T_cam_model (4×4 m)}] visible or not. An unlabeled video
        (recorded data) passes ``inst=None`` and ``objects=None``: no ground truth is written."""
        write_rgb(self._frame(FRAME_RGB, frame_id), rgb)
        write_depth_m(self._frame(FRAME_DEPTH, frame_id), depth_m, depth_scale)
        if inst is not None:
            write_inst(self._frame(FRAME_MASK_INST, frame_id), inst)
        self.cameras[str(frame_id)] = camera_record(K, T_world_cam, depth_scale)
        if objects is not None:
            self.gts[str(frame_id)] = [gt_record(o["obj_id"], o["inst_id"], o["T_cam_model"]) for o in objects]

    def finish(self, scene_info: dict | None) -> None:
        """Write the JSON records (ground truth only if frames had labels); scene_camera.json last,
        since it marks a complete video."""
        if scene_info is not None:
            write_json(self.dir / GT_JSON, self.gts)
            write_json(self.dir / INFO_JSON, scene_info)
        write_json(self.dir / CAMERA_JSON, self.cameras)
