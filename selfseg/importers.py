"""Recorded RGB-D videos → the selfseg dataset format, with or without labels (the ``import_videos`` command:
:mod:`selfseg.cli`).

    import_videos --format ycb-video|tum|folder SRC [SRC ...] --out DIR [--frame-step N]
                  [--resolution WxH] [--intrinsics K.txt | --camera freiburg1] [--depth-scale MM]
                  [--max-dt-s 0.02]

Each SRC is one video folder of the format, or a folder whose sub-folders (sorted) are video folders:

- ``ycb-video``: ``NNNNNN-color.png``, ``-depth.png`` (uint16), ``-meta.mat`` (``intrinsic_matrix``,
  ``factor_depth`` units per metre, ``cls_indexes``, ``poses`` 3×4×N, metres), optional ``-label.png``
  (class ids; YCB-Video holds one instance per class, so instance id = class id);
- ``tum``: ``rgb.txt`` and ``depth.txt`` (``timestamp path`` lines), depth factor 5000 per metre,
  optional ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``, world ← camera); colour and depth
  are associated by nearest timestamp within ``--max-dt-s`` (each depth frame used at most once);
  intrinsics from ``--intrinsics`` or ``--camera`` (the TUM calibrations below);
- ``folder``: ``rgb/*.png|jpg``, ``depth/*.png`` (uint16; mm = value × ``--depth-scale``) paired by
  file stem, ``intrinsics.txt`` (or ``--intrinsics``), optional ``mask_inst/*.png`` (uint16 instance ids).

In ``ycb-video`` and ``folder`` every depth and label frame needs its colour frame: an unpaired one is bad input.

Intrinsics files hold ``fx fy cx cy`` or a 3×3 matrix, OpenCV pixel-centre convention. Frames keep
their index in the source order as frame id (``--frame-step`` keeps every N-th); ``--resolution``
resizes colour (area), depth and labels (nearest) and scales K. Without labels the videos carry no
``mask_inst/``/``scene_gt.json`` (valid for ``train``/``segment``; ``evaluate`` refuses them). Camera
poses are the dataset's (YCB-Video has none per frame: identity; TUM: ``groundtruth.txt`` if present).

Each video is written into a temporary folder and renamed when complete, so an interrupted import
resumes at the first missing video; all writing goes through :class:`selfseg.writers.VideoWriter`.
Bad input prints one line naming the file and the problem and exits with status 2.
"""
from __future__ import annotations

import argparse
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from selfseg.dataset import (CAMERA_JSON, DATASET_INFO, MASK_INST_DIR, VIDEO_DIR, Dataset, DatasetError, read_depth_m,
                             read_inst, read_rgb, validate_K, video_id_str)
from selfseg.fileio import atomic_dir, read_json
from selfseg.manifest import write_manifest
from selfseg.writers import VideoWriter, write_dataset_info

IMPORTER_VERSION = 1
FORMATS = ("ycb-video", "tum", "folder")
TUM_DEPTH_FACTOR = 5000.0  # depth PNG units per metre
# TUM RGB-D calibrations (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats): fx fy cx cy
TUM_CAMERAS = {"freiburg1": (517.3, 516.5, 318.6, 255.3), "freiburg2": (520.9, 521.0, 325.1, 249.7),
               "freiburg3": (535.4, 539.2, 320.1, 247.6)}
IMAGE_EXTS = (".png", ".jpg", ".jpeg")


@dataclass
class SourceFrame:
    """One frame of a recorded video, not yet read: paths, intrinsics, depth scale (mm/unit), pose."""

    rgb: Path
    depth: Path
    K: np.ndarray
    depth_scale_mm: float
    T_world_cam: np.ndarray
    label: Path | None = None  # instance (folder) or class (YCB-Video) map
    objects: list[dict] | None = None  # [{obj_id, inst_id, T_cam_model}] when known


@dataclass
class SourceVideo:
    source: Path
    frames: list[SourceFrame]
    labeled: bool
    instances: dict[int, int] | None = None  # inst id → obj id, for labelled videos


def read_intrinsics(path: Path) -> np.ndarray:
    """``fx fy cx cy`` or a 3×3 matrix (whitespace/comma separated) → 3×3 K."""
    try:
        vals = [float(v) for v in re.split(r"[\s,]+", Path(path).read_text().strip()) if v]
    except FileNotFoundError:
        raise DatasetError(f"{path}: intrinsics file missing") from None
    except ValueError:
        raise DatasetError(f"{path}: intrinsics must be numbers ('fx fy cx cy' or a 3×3 matrix)") from None
    if len(vals) == 4:
        fx, fy, cx, cy = vals
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    if len(vals) == 9:
        return np.array(vals, dtype=np.float64).reshape(3, 3)
    raise DatasetError(f"{path}: intrinsics must hold 4 values (fx fy cx cy) or 9 (3×3 matrix), found {len(vals)}")


def scale_K(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics of an image resized by (sx, sy), pixel-centre convention: c' = (c + ½)·s − ½."""
    K2 = np.array(K, dtype=np.float64)
    K2[0, 0] *= sx
    K2[0, 1] *= sx
    K2[1, 1] *= sy
    K2[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K2[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K2


def image_files(folder: Path) -> dict[str, Path]:
    """The folder's colour/depth/mask images by stem (``IMAGE_EXTS``), sorted; {} if it is no folder."""
    return {p.stem: p for p in sorted(folder.iterdir()) if p.suffix.lower() in IMAGE_EXTS} if folder.is_dir() else {}


# ---- formats: each lists a video folder's frames --------------------------------------------
def is_video(fmt: str, folder: Path) -> bool:
    if fmt == "ycb-video":
        return any(folder.glob("*-color.png"))
    if fmt == "tum":
        return (folder / "rgb.txt").is_file()
    return (folder / "rgb").is_dir()


def folder_video(src: Path, K_override: np.ndarray | None, depth_scale_mm: float) -> SourceVideo:
    rgbs, depths, masks = image_files(src / "rgb"), image_files(src / "depth"), image_files(src / "mask_inst")
    if not rgbs:
        raise DatasetError(f"{src / 'rgb'}: no .png/.jpg frames")
    missing = [s for s in rgbs if s not in depths]
    if missing:
        raise DatasetError(f"{src / 'depth'}: no depth frame for colour frame {rgbs[missing[0]].name} "
                           f"({len(missing)} missing)")
    for sub, extra in (("depth", depths), ("mask_inst", masks)):
        unpaired = [s for s in extra if s not in rgbs]
        if unpaired:
            raise DatasetError(f"{extra[unpaired[0]]}: no colour frame {unpaired[0]}.* in {src / 'rgb'} for this "
                               f"{sub} frame ({len(unpaired)} unpaired)")
    labeled = bool(masks)
    if labeled and any(s not in masks for s in rgbs):
        s = next(s for s in rgbs if s not in masks)
        raise DatasetError(f"{src / 'mask_inst'}: no instance map for colour frame {rgbs[s].name}")
    K = K_override if K_override is not None else read_intrinsics(src / "intrinsics.txt")
    eye = np.eye(4)
    frames = [SourceFrame(rgbs[s], depths[s], K, depth_scale_mm, eye, masks.get(s), [] if labeled else None)
              for s in rgbs]
    return SourceVideo(src, frames, labeled)


def _tum_list(path: Path) -> list[tuple[float, str]]:
    """``timestamp rest...`` lines of a TUM list file ('#' comments skipped)."""
    out = []
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing file") from None
    for i, line in enumerate(lines, 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        try:
            out.append((float(parts[0]), " ".join(parts[1:])))
        except (ValueError, IndexError):
            raise DatasetError(f"{path} line {i}: expected 'timestamp ...', got {line!r}") from None
    return out


def associate(a: list[float], b: list[float], max_dt_s: float) -> list[tuple[int, int]]:
    """Pairs (i, j) of timestamps with |a_i − b_j| ≤ max_dt_s, closest first, each index used once; sorted by i."""
    if not a or not b:
        return []
    A, B = np.asarray(a), np.asarray(b)
    diff = np.abs(A[:, None] - B[None, :])
    ii, jj = np.nonzero(diff <= max_dt_s)
    pairs, used_a, used_b = [], set(), set()
    for k in np.argsort(diff[ii, jj], kind="stable"):
        i, j = int(ii[k]), int(jj[k])
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def _quat_pose(vals: list[float]) -> np.ndarray:
    """tx ty tz qx qy qz qw → 4×4 T_world_cam."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(vals[3:7]).as_matrix()
    T[:3, 3] = vals[:3]
    return T


def tum_video(src: Path, K: np.ndarray | None, max_dt_s: float) -> SourceVideo:
    if K is None:
        raise DatasetError(f"{src}: TUM intrinsics missing: give --intrinsics K.txt or --camera "
                           f"{'|'.join(TUM_CAMERAS)}")
    rgb, depth = _tum_list(src / "rgb.txt"), _tum_list(src / "depth.txt")
    pairs = associate([t for t, _ in rgb], [t for t, _ in depth], max_dt_s)
    if not pairs:
        raise DatasetError(f"{src / 'depth.txt'}: no depth frame lies within {max_dt_s} s of any of the "
                           f"{len(rgb)} colour frames of {src / 'rgb.txt'}")
    poses = None
    gt_path = src / "groundtruth.txt"
    if gt_path.is_file():
        gt = _tum_list(gt_path)
        gpairs = dict(associate([rgb[i][0] for i, _ in pairs], [t for t, _ in gt], max_dt_s))
        if len(gpairs) < len(pairs):
            i = next(k for k in range(len(pairs)) if k not in gpairs)
            raise DatasetError(f"{gt_path}: no pose within {max_dt_s} s of colour frame {rgb[pairs[i][0]][1]}")
        try:
            poses = [_quat_pose([float(v) for v in gt[gpairs[k]][1].split()]) for k in range(len(pairs))]
        except (ValueError, IndexError):
            raise DatasetError(f"{gt_path}: pose lines must be 'timestamp tx ty tz qx qy qz qw'") from None
    frames = [SourceFrame(src / rgb[i][1], src / depth[j][1], K, 1000.0 / TUM_DEPTH_FACTOR,
                          poses[k] if poses else np.eye(4)) for k, (i, j) in enumerate(pairs)]
    return SourceVideo(src, frames, labeled=False)


def ycb_video(src: Path, K_override: np.ndarray | None) -> SourceVideo:
    from scipy.io import loadmat

    colors = sorted(src.glob("*-color.png"))
    stems = {c.name[:-len("-color.png")] for c in colors}
    for kind in ("depth", "label"):
        unpaired = [p for p in sorted(src.glob(f"*-{kind}.png")) if p.name[:-len(f"-{kind}.png")] not in stems]
        if unpaired:
            raise DatasetError(f"{unpaired[0]}: no -color.png frame for this {kind} frame ({len(unpaired)} unpaired)")
    frames, labeled, instances = [], None, {}
    for c in colors:
        stem = c.name[:-len("-color.png")]
        meta_path = src / f"{stem}-meta.mat"
        if not meta_path.is_file():
            raise DatasetError(f"{meta_path}: missing (YCB-Video frames need -meta.mat for intrinsics and depth factor)")
        try:
            meta = loadmat(meta_path)
            factor = float(np.asarray(meta["factor_depth"]).reshape(-1)[0])
            K = K_override if K_override is not None else np.asarray(meta["intrinsic_matrix"], np.float64).reshape(3, 3)
            cls = np.asarray(meta.get("cls_indexes", np.zeros(0)), np.int64).reshape(-1)
            poses = np.asarray(meta["poses"], np.float64).reshape(3, 4, -1) if "poses" in meta else np.zeros((3, 4, 0))
        except (KeyError, ValueError, TypeError, IndexError) as e:
            raise DatasetError(f"{meta_path}: malformed -meta.mat ({e!r}); needs intrinsic_matrix, factor_depth") from None
        except Exception as e:  # scipy raises assorted errors on a corrupt .mat
            raise DatasetError(f"{meta_path}: unreadable .mat file ({e})") from None
        if not factor > 0:
            raise DatasetError(f"{meta_path}: factor_depth must be positive, got {factor}")
        label = src / f"{stem}-label.png"
        has_label = label.is_file()
        if labeled is None:
            labeled = has_label
        elif has_label != labeled:
            raise DatasetError(f"{label}: labels are present for some frames of {src} but not others")
        objects = None
        if labeled:
            objects = []
            for k, c_id in enumerate(cls):
                T = np.eye(4)
                if k < poses.shape[2]:
                    T[:3, :] = poses[:, :, k]
                objects.append({"obj_id": int(c_id), "inst_id": int(c_id), "T_cam_model": T})
                instances[int(c_id)] = int(c_id)
        frames.append(SourceFrame(c, src / f"{stem}-depth.png", K, 1000.0 / factor, np.eye(4),
                                  label if labeled else None, objects))
    return SourceVideo(src, frames, bool(labeled), instances if labeled else None)


def list_videos(fmt: str, sources: list[Path], K: np.ndarray | None, depth_scale_mm: float,
                max_dt_s: float) -> list[SourceVideo]:
    """Every video folder under ``sources`` (each SRC a video or a folder of videos), parsed."""
    folders = []
    for src in sources:
        if not src.is_dir():
            raise DatasetError(f"{src}: source folder not found")
        if is_video(fmt, src):
            folders.append(src)
        else:
            subs = [p for p in sorted(src.iterdir()) if p.is_dir() and is_video(fmt, p)]
            if not subs:
                raise DatasetError(f"{src}: neither a {fmt} video folder nor a folder of them")
            folders += subs
    if fmt == "ycb-video":
        return [ycb_video(f, K) for f in folders]
    if fmt == "tum":
        return [tum_video(f, K, max_dt_s) for f in folders]
    return [folder_video(f, K, depth_scale_mm) for f in folders]


# ---- conversion --------------------------------------------------------------------------------
def _read_frame(fr: SourceFrame, where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    rgb = read_rgb(fr.rgb)
    depth = read_depth_m(fr.depth, fr.depth_scale_mm)
    if depth.shape != rgb.shape[:2]:
        raise DatasetError(f"{fr.depth}: depth is {depth.shape[1]}×{depth.shape[0]} but colour {fr.rgb.name} is "
                           f"{rgb.shape[1]}×{rgb.shape[0]}")
    label = read_inst(fr.label) if fr.label is not None else None
    if label is not None and label.shape != rgb.shape[:2]:
        raise DatasetError(f"{fr.label}: label map is {label.shape[1]}×{label.shape[0]} but colour is "
                           f"{rgb.shape[1]}×{rgb.shape[0]}")
    validate_K(fr.K, rgb.shape[1], rgb.shape[0], where)
    return rgb, depth, label


def import_video(video: SourceVideo, out_dir: Path, frame_step: int, resolution: tuple[int, int] | None,
                 size: tuple[int, int], progress: bool = True) -> None:
    """Convert one video into ``out_dir`` (atomically); every frame must end up ``size`` = (W, H)."""
    with atomic_dir(out_dir) as tmp:
        writer = VideoWriter(tmp)
        for fid, fr in tqdm(list(enumerate(video.frames))[::frame_step], desc=f"import {video.source.name}",
                            unit="frame", disable=not progress, leave=False):
            rgb, depth, label = _read_frame(fr, f"{video.source} frame {fr.rgb.name}")
            K = fr.K
            h, w = depth.shape
            if resolution is not None and resolution != (w, h):
                W, H = resolution
                rgb = cv2.resize(rgb, (W, H), interpolation=cv2.INTER_AREA)
                depth = cv2.resize(depth, (W, H), interpolation=cv2.INTER_NEAREST)
                if label is not None:
                    label = cv2.resize(label, (W, H), interpolation=cv2.INTER_NEAREST)
                K = scale_K(K, W / w, H / h)
                h, w = H, W
            if size != (w, h):
                raise DatasetError(f"{fr.rgb}: frame is {w}×{h} but the dataset is {size[0]}×{size[1]} "
                                   f"(give --resolution WxH to resize every video)")
            writer.write_frame(fid, rgb, depth, label, K, fr.T_world_cam, fr.objects, fr.depth_scale_mm)
        info = None
        if video.labeled:
            ids = video.instances if video.instances is not None else {
                int(i): int(i) for i in sorted({int(v) for p in (tmp / MASK_INST_DIR).iterdir() for v in np.unique(read_inst(p))} - {0})}
            info = {"instances": {str(k): v for k, v in sorted(ids.items())}, "source": str(video.source)}
        writer.finish(info)


def run(args: argparse.Namespace) -> int:
    """The ``import_videos`` command on parsed arguments (:func:`selfseg.cli.import_videos_parser`)."""
    if args.frame_step < 1:
        raise DatasetError(f"--frame-step must be ≥ 1, got {args.frame_step}")
    if not args.depth_scale > 0:
        raise DatasetError(f"--depth-scale must be positive, got {args.depth_scale}")
    K = read_intrinsics(args.intrinsics) if args.intrinsics else (
        np.array([[TUM_CAMERAS[args.camera][0], 0, TUM_CAMERAS[args.camera][2]],
                  [0, TUM_CAMERAS[args.camera][1], TUM_CAMERAS[args.camera][3]], [0, 0, 1.0]]) if args.camera else None)
    videos = list_videos(args.format, [Path(s) for s in args.sources], K, args.depth_scale, args.max_dt_s)
    options = {"format": args.format, "sources": [str(v.source.resolve()) for v in videos],
               "frame_step": args.frame_step, "resolution": list(args.resolution) if args.resolution else None,
               "intrinsics": str(args.intrinsics) if args.intrinsics else args.camera,
               "depth_scale": args.depth_scale, "max_dt_s": args.max_dt_s, "importer_version": IMPORTER_VERSION}
    out = Path(args.out)
    info_path = out / DATASET_INFO
    if info_path.is_file():  # resume: only an import with the same sources and options
        if read_json(info_path).get("import") != options:
            raise DatasetError(f"{info_path}: {out} holds another dataset or import options; choose another --out")
    elif out.exists() and any(out.iterdir()):
        raise DatasetError(f"{out}: exists and is not an import of these videos; choose an empty or new --out")
    else:
        first = videos[0].frames[0]
        size = args.resolution or _read_frame(first, f"{videos[0].source} frame {first.rgb.name}")[0].shape[1::-1]
        write_dataset_info(out, {"name": args.name or out.name, "generator_version": f"import_videos {IMPORTER_VERSION}",
                                 "resolution": list(size), "seed": 0, "objects": [], "import": options,
                                 "labeled": all(v.labeled for v in videos)})
    size = tuple(read_json(info_path)["resolution"])
    done = 0
    for i, video in enumerate(tqdm(videos, desc="import_videos", unit="video", disable=args.quiet)):
        vdir = out / VIDEO_DIR.format(video_id=video_id_str(i))
        if (vdir / CAMERA_JSON).is_file():
            done += 1
            continue
        import_video(video, vdir, args.frame_step, args.resolution, size, progress=not args.quiet)
    ds = Dataset(out)
    print(f"{ds}: {len(videos) - done} imported, {done} already present; "
          f"{'labelled' if ds.has_labels() else 'unlabeled (train/segment only; evaluate needs labels)'}; "
          f"manifest hash {write_manifest(out)}")
    return 0

