"""The selfseg dataset format: the one module that owns the path templates, and its readers
(writers: :mod:`selfseg.writers`; pose maths: :mod:`selfseg.poses`).

On disk (BOP scene layout, so bop_toolkit-style readers work)::

    DATASET/
      dataset_info.json        format_version, generator_version, name, resolution [W, H],
                               full resolved config, seed, objects [{obj_id, name, ...}]
      models/obj_000001.ply    object meshes in millimetres, models/models_info.json
      videos/000000/
        rgb/000000.png         8-bit RGB
        depth/000000.png       uint16 planar z; millimetres = value * depth_scale
        mask_inst/000000.png   uint16 instance ids: 0 = background/table, k >= 1 = instance k
        scene_camera.json      {frame: {cam_K (9), depth_scale, cam_R_w2c (9), cam_t_w2c (3, mm)}}
        scene_gt.json          {frame: [{obj_id, inst_id, cam_R_m2c (9), cam_t_m2c (3, mm)}]}
        scene_info.json        {instances {inst_id: obj_id}, object world poses, table plane, orbit, seed}

In memory: depth in metres (float32, 0 = no measurement), RGB uint8 H×W×3 in RGB order,
instance maps uint16, ``K`` 3×3 float64 in the OpenCV pixel-centre convention (the centre of
pixel (u, v) is at integer coordinates, so a W-wide image from Blender has cx = W/2 − 0.5),
poses as 4×4 float64 ``T_a_b`` mapping points from frame b into frame a. The camera frame is
OpenCV's: x right, y down, z forward.

Ground truth (``mask_inst/``, ``scene_gt.json``, ``scene_info.json``) is reachable only through
:class:`LabeledVideo`. Methods get :class:`Video`, which has no labels (``evaluate`` runs them in a
sandbox where only the files they may read exist, :mod:`selfseg.eval.sandbox`).
"""
from __future__ import annotations

import fnmatch
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from selfseg.fileio import read_json
from selfseg.manifest import content_hash, manifest_hash, scan
from selfseg.poses import invert_T, rt_to_T

FORMAT_VERSION = 1
DEPTH_SCALE_MM = 0.1  # millimetres per unit of the depth PNG: 0.1 mm steps, up to 6.55 m

# ---- path templates: inside a video folder ---------------------------------------------------
MASK_INST_DIR = "mask_inst"
FRAME_RGB = "rgb/{frame_id:06d}.png"
FRAME_DEPTH = "depth/{frame_id:06d}.png"
FRAME_MASK_INST = MASK_INST_DIR + "/{frame_id:06d}.png"
CAMERA_JSON = "scene_camera.json"
GT_JSON = "scene_gt.json"
INFO_JSON = "scene_info.json"

# ---- path templates: relative to the dataset root ---------------------------------------------
DATASET_INFO = "dataset_info.json"
MODELS_DIR = "models"
MODEL_PLY = MODELS_DIR + "/obj_{obj_id:06d}.ply"
MODELS_INFO = MODELS_DIR + "/models_info.json"
VIDEOS_DIR = "videos"
VIDEO_DIR = VIDEOS_DIR + "/{video_id}"
RGB = VIDEO_DIR + "/" + FRAME_RGB
RGB_GLOB = VIDEO_DIR.format(video_id="*") + "/rgb/*.png"  # every video's RGB frames (fnmatch pattern)
DEPTH = VIDEO_DIR + "/" + FRAME_DEPTH
MASK_INST = VIDEO_DIR + "/" + FRAME_MASK_INST
SCENE_CAMERA = VIDEO_DIR + "/" + CAMERA_JSON
SCENE_GT = VIDEO_DIR + "/" + GT_JSON
SCENE_INFO = VIDEO_DIR + "/" + INFO_JSON

GROUND_TRUTH_NAMES = (MASK_INST_DIR, GT_JSON, INFO_JSON)


def video_id_str(index: int) -> str:
    return f"{index:06d}"


class DatasetError(ValueError):
    """Bad or inconsistent dataset content; the message names the file and the problem."""


# ---- image readers ------------------------------------------------------------------------
def _read_bytes(path: Path) -> bytes:
    # Reads go through Python's open() so that the ground-truth guard (an audit hook) sees them.
    try:
        with open(path, "rb") as f:
            return f.read()
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing file") from None


def _decode_png(path: Path, flags: int) -> np.ndarray:
    import cv2

    data = _read_bytes(path)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags) if data else None
    if img is None:
        raise DatasetError(f"{path}: corrupt or unreadable image")
    return img


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """8-bit PNG/JPEG → uint8 H×W×3 in RGB order."""
    import cv2

    img = _decode_png(Path(path), cv2.IMREAD_COLOR)
    return np.ascontiguousarray(img[:, :, ::-1])


def read_depth_m(path: str | os.PathLike, depth_scale: float) -> np.ndarray:
    """uint16 depth PNG → float32 metres (0 = no measurement). mm = value * depth_scale."""
    import cv2

    raw = _decode_png(Path(path), cv2.IMREAD_UNCHANGED)
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise DatasetError(f"{path}: depth must be a single-channel uint16 PNG, got {raw.dtype} {raw.shape}")
    return raw.astype(np.float32) * np.float32(depth_scale / 1000.0)


def read_inst(path: str | os.PathLike) -> np.ndarray:
    """uint16 instance PNG → uint16 H×W (0 = background)."""
    import cv2

    raw = _decode_png(Path(path), cv2.IMREAD_UNCHANGED)
    if raw.ndim != 2 or raw.dtype not in (np.uint16, np.uint8):
        raise DatasetError(f"{path}: instance map must be a single-channel uint16 PNG, got {raw.dtype} {raw.shape}")
    return raw.astype(np.uint16)


# ---- camera records -------------------------------------------------------------------------
@dataclass(frozen=True)
class CameraFrame:
    """One frame's camera: intrinsics (OpenCV pixel-centre convention), depth scale, pose."""

    K: np.ndarray  # 3×3
    depth_scale: float  # mm per depth-PNG unit
    T_world_cam: np.ndarray  # 4×4, metres


def validate_K(K: np.ndarray, width: int, height: int, where: str) -> None:
    """Reject intrinsics that cannot belong to a W×H pinhole camera."""
    K = np.asarray(K, dtype=np.float64)
    problems = []
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        problems.append("K must be a finite 3×3 matrix")
    else:
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            problems.append(f"focal lengths must be positive (fx={K[0, 0]}, fy={K[1, 1]})")
        if not (0 <= K[0, 2] <= width) or not (0 <= K[1, 2] <= height):
            problems.append(f"principal point ({K[0, 2]}, {K[1, 2]}) lies outside the {width}×{height} image")
        if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            problems.append("K must be upper-triangular with K[2,2] = 1")
    if problems:
        raise DatasetError(f"{where}: wrong intrinsics: " + "; ".join(problems))


def _parse_scene_camera(path: Path, width: int, height: int) -> dict[int, CameraFrame]:
    raw = read_json(path)
    if not isinstance(raw, dict) or not raw:
        raise DatasetError(f"{path}: no camera records")
    cams = {}
    for key, rec in raw.items():
        where = f"{path} frame {key}"
        try:
            fid = int(key)
            K = np.asarray(rec["cam_K"], dtype=np.float64).reshape(3, 3)
            depth_scale = float(rec["depth_scale"])
            T_cam_world = rt_to_T(rec["cam_R_w2c"], rec["cam_t_w2c"])
        except (KeyError, ValueError, TypeError) as e:
            raise DatasetError(f"{where}: malformed camera record ({e!r})") from None
        validate_K(K, width, height, where)
        if not (depth_scale > 0 and np.isfinite(depth_scale)):
            raise DatasetError(f"{where}: depth_scale must be positive, got {depth_scale}")
        if not np.all(np.isfinite(T_cam_world)):
            raise DatasetError(f"{where}: camera pose contains NaN or inf")
        cams[fid] = CameraFrame(K, depth_scale, invert_T(T_cam_world))
    return dict(sorted(cams.items()))


# ---- videos --------------------------------------------------------------------------------
class PosesNotGiven(RuntimeError):
    """Camera poses were requested from a video opened without ``poses_given=True``."""


class Video:
    """An unlabeled RGB-D video: everything a method may see, and nothing more.

    Frames are read lazily. ``T_world_cam`` is available only when the video was opened with
    ``poses_given=True`` (the ground-truth-pose ablation); by default methods estimate poses.
    """

    def __init__(self, root: Path, video_id: str, width: int, height: int, poses_given: bool = False):
        self._root = Path(root)
        self.video_id = video_id
        self.width = width
        self.height = height
        self.poses_given = poses_given
        self._cams = _parse_scene_camera(self._path(SCENE_CAMERA), width, height)
        self.frame_ids: list[int] = list(self._cams)

    def _path(self, template: str, frame_id: int | None = None) -> Path:
        return self._root / template.format(video_id=self.video_id, frame_id=frame_id or 0)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.video_id!r}, {len(self.frame_ids)} frames, {self.width}x{self.height})"

    @property
    def root(self) -> Path:
        """The dataset folder (for cache keys; ground-truth files in it stay guarded)."""
        return self._root

    def __len__(self) -> int:
        return len(self.frame_ids)

    def _cam(self, frame_id: int) -> CameraFrame:
        try:
            return self._cams[frame_id]
        except KeyError:
            raise DatasetError(f"{self._path(SCENE_CAMERA)}: no camera record for frame {frame_id}") from None

    def K(self, frame_id: int | None = None) -> np.ndarray:
        """3×3 intrinsics (OpenCV pixel-centre convention) of a frame (default: the first)."""
        return self._cam(self.frame_ids[0] if frame_id is None else frame_id).K.copy()

    def _check_shape(self, img: np.ndarray, path: Path) -> np.ndarray:
        if img.shape[:2] != (self.height, self.width):
            raise DatasetError(f"{path}: image is {img.shape[1]}×{img.shape[0]}, expected {self.width}×{self.height}")
        return img

    def rgb(self, frame_id: int) -> np.ndarray:
        """uint8 H×W×3, RGB order."""
        self._cam(frame_id)
        p = self._path(RGB, frame_id)
        return self._check_shape(read_rgb(p), p)

    def depth_m(self, frame_id: int) -> np.ndarray:
        """float32 H×W planar depth in metres along the camera z axis; 0 = no measurement."""
        p = self._path(DEPTH, frame_id)
        return self._check_shape(read_depth_m(p, self._cam(frame_id).depth_scale), p)

    def T_world_cam(self, frame_id: int) -> np.ndarray:
        """4×4 camera-to-world pose (metres); only for videos opened with ``poses_given=True``."""
        if not self.poses_given:
            raise PosesNotGiven(f"video {self.video_id}: camera poses are not given to methods "
                                "(open it with poses_given=True for the ground-truth-pose ablation)")
        return self._cam(frame_id).T_world_cam.copy()


class LabeledVideo(Video):
    """A video with its ground truth: for the evaluator, the generator's tests and supervised baselines."""

    def __init__(self, root: Path, video_id: str, width: int, height: int):
        super().__init__(root, video_id, width, height, poses_given=True)
        self._gt: dict | None = None
        self._info: dict | None = None

    def inst(self, frame_id: int) -> np.ndarray:
        """uint16 H×W instance map: 0 = background/table, k >= 1 = the scene's instance k."""
        self._cam(frame_id)
        p = self._path(MASK_INST, frame_id)
        return self._check_shape(read_inst(p), p)

    @property
    def scene_info(self) -> dict:
        if self._info is None:
            self._info = read_json(self._path(SCENE_INFO))
        return self._info

    def gt(self, frame_id: int) -> list[dict]:
        """Objects in a frame: [{obj_id, inst_id, T_cam_model (4×4, metres)}]."""
        if self._gt is None:
            self._gt = read_json(self._path(SCENE_GT))
        try:
            recs = self._gt[str(frame_id)]
        except KeyError:
            raise DatasetError(f"{self._path(SCENE_GT)}: no record for frame {frame_id}") from None
        return [{"obj_id": r["obj_id"], "inst_id": r["inst_id"], "T_cam_model": rt_to_T(r["cam_R_m2c"], r["cam_t_m2c"])}
                for r in recs]

    def instance_to_object(self) -> dict[int, int]:
        """Instance id → object id for this video."""
        return {int(k): int(v) for k, v in self.scene_info["instances"].items()}


class Dataset:
    """A selfseg dataset folder."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        info_path = self.root / DATASET_INFO
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: dataset folder not found")
        if not info_path.is_file():
            raise DatasetError(f"{info_path}: missing; {self.root} is not a selfseg dataset")
        self.info: dict = read_json(info_path)
        version = self.info.get("format_version")
        if version != FORMAT_VERSION:
            raise DatasetError(f"{info_path}: format_version {version!r}, this selfseg reads {FORMAT_VERSION}")
        try:
            self.width, self.height = (int(v) for v in self.info["resolution"])
        except (KeyError, TypeError, ValueError):
            raise DatasetError(f"{info_path}: missing or malformed 'resolution' [W, H]") from None
        self.name: str = self.info.get("name", self.root.name)
        vdir = self.root / VIDEOS_DIR
        self.video_ids: list[str] = sorted(
            p.name for p in vdir.iterdir() if (p / CAMERA_JSON).is_file()) if vdir.is_dir() else []
        if not self.video_ids:
            raise DatasetError(f"{vdir}: the dataset has no videos")

    def __repr__(self) -> str:
        return f"Dataset({str(self.root)!r}, {len(self.video_ids)} videos, {self.width}x{self.height})"

    def _check_id(self, video_id: str) -> None:
        if video_id not in self.video_ids:
            raise DatasetError(f"{self.root}: no video {video_id!r} (have {', '.join(self.video_ids)})")

    def video(self, video_id: str, poses_given: bool = False) -> Video:
        """The unlabeled view of a video, as given to methods."""
        self._check_id(video_id)
        return Video(self.root, video_id, self.width, self.height, poses_given=poses_given)

    def labeled(self, video_id: str) -> LabeledVideo:
        """The video with ground truth (evaluation and supervised baselines only)."""
        self._check_id(video_id)
        return LabeledVideo(self.root, video_id, self.width, self.height)

    @property
    def seed(self) -> int:
        return int(self.info.get("seed", 0))

    def model_path(self, obj_id: int) -> Path:
        return self.root / MODEL_PLY.format(obj_id=obj_id)

    def models_info(self) -> dict[int, dict]:
        return {int(k): v for k, v in read_json(self.root / MODELS_INFO).items()}

    def has_labels(self) -> bool:
        """Whether every video has ground truth (imported recordings may have none)."""
        return all((self.root / SCENE_GT.format(video_id=v)).is_file() for v in self.video_ids)

    def content_hash(self) -> str:
        """The dataset's identity: a hash of every file's size and content (:mod:`selfseg.manifest`)."""
        return content_hash(self.root)


# ---- identities built on the manifest (selfseg.manifest) that depend on which file is what ---------------
# RGB frames are the one part of a generated dataset that depends on the CPU: Cycles, Embree and
# OpenImageDenoise choose their SIMD kernels by CPUID, and their last-bit float differences flip a few 8-bit
# values per frame by 1 (PSNR above 90 dB between CPU types). Depth, masks, poses, cameras and meshes are
# byte-identical on every x86-64 CPU measured: :func:`geometry_hash` is their identity, and
# :func:`only_rgb_differs` tells a CPU-dependent RGB difference (from :func:`selfseg.manifest.differences`)
# apart from any other.


def is_rgb_frame(path: str) -> bool:
    """Whether the manifest path (``/``-separated) is a video's RGB frame."""
    return fnmatch.fnmatchcase(path, RGB_GLOB)


def geometry_hash(files: dict[str, list]) -> str:
    """The identity of a file listing without its RGB frames (depth, masks, poses, cameras, meshes,
    records): the part of a generated dataset that is the same on every CPU (16 hex digits)."""
    return manifest_hash({p: v for p, v in files.items() if not is_rgb_frame(p)})


def only_rgb_differs(found: dict[str, str]) -> bool:
    """Whether every difference of :func:`selfseg.manifest.differences` is a changed RGB frame (none missing or extra): the
    class of difference rendering on another CPU type gives."""
    return bool(found) and all(is_rgb_frame(p) and "differs" in k for p, k in found.items())


def video_content_hash(video: Video) -> str:
    """Identity of what a method reads of one :class:`Video` (its rgb/ and depth/ frames and
    scene_camera.json), for stage and cache keys; cheap scan. Lists no folder, so ground truth stays unread."""
    rels = [t.format(video_id=video.video_id, frame_id=f) for t in (RGB, DEPTH) for f in video.frame_ids]
    return manifest_hash(scan(video.root, only=rels + [SCENE_CAMERA.format(video_id=video.video_id)]))
