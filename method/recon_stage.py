"""The reconstruction stage: one video → fused scene, poses, support plane, object points, foreground masks.

Stage folder ``cache.path("recon", video_id)/``::

    cloud.npz      points_w (N×3 f32, m), colors (N×3 f32 in [0, 1]), normals_w (N×3 f32, unit):
                   the object points kept after background removal, world frame
    poses.npz      frame_ids (F int64, every frame of the video), T_world_cam (F×4×4 f64; NaN where
                   no pose exists: frames before the first usable one), tracking_ok (F bool: tracked
                   or given and fused; False: predicted pose, not fused)
    plane.json     plane [a, b, c, d] (unit normal up: height = a·x + b·y + c·z + d), up_hint
    tsdf.npz       the fused open3d VoxelBlockGrid (attributes tsdf, weight, color): the arrays of its
                   ``save()``, zip-compressed (4× smaller; open3d reads only uncompressed npz, see
                   :func:`save_grid` / :func:`load_grid`)
    volume.json    voxel_size_m, block_resolution, trunc_m, K (3×3, OpenCV convention)
    keyframes.npz  frame_ids, T_world_cam (F×4×4), depth_m (F×H×W f32): free-space evidence
    fg/{fid:06d}.png  uint8 0/255 foreground mask of each frame: the kept points projected with
                   the frame's pose through a z-buffer with a depth test against the frame's depth,
                   minus pixels whose measured point lies on or below the support plane
    report.json    world frame, point counts, tracking failures, timings (s)
    stage.json     the cache key (see :mod:`selfseg.stages`)

The world frame is the first camera's frame for estimated poses, the dataset's with
``use_gt_poses``. :func:`load_recon` reads it back.
"""
from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from selfseg.config import to_dict
from selfseg.dataset import Video, video_content_hash
from selfseg.fileio import hash_json, read_json, write_json
from selfseg.method.background import BackgroundConfig, plane_pixels, remove_support_plane, up_hint_from_poses
from selfseg.method.projection import foreground_mask
from selfseg.method.reconstruct import ReconConfig, Volume, occupancy, reconstruct
from selfseg.stages import STAGE_FILE, StageCache

STAGE = "recon"
CODE_VERSION = 2

# The stage's files, relative to its folder (contents: the module docstring).
CLOUD_NPZ = "cloud.npz"  # object points after background removal: points_w (m), colors, normals_w; world frame
POSES_NPZ = "poses.npz"  # every frame's T_world_cam (m; NaN without a pose) and tracking_ok
PLANE_JSON = "plane.json"  # the support plane [a, b, c, d] (world frame, m, unit normal up) and the up hint
TSDF_NPZ = "tsdf.npz"  # the fused open3d VoxelBlockGrid (tsdf, weight, color), world frame
VOLUME_JSON = "volume.json"  # the TSDF's voxel_size_m, block_resolution, trunc_m and K (3×3, OpenCV)
KEYFRAMES_NPZ = "keyframes.npz"  # keyframe ids, T_world_cam and depth_m (F×H×W, m): free-space evidence
FG_PNG = "fg/{frame_id:06d}.png"  # a frame's projected foreground mask (uint8 0/255, image size)
REPORT_JSON = "report.json"  # world frame, point counts, tracking failures, timings (s)


def recon_key(video: Video, cfg: ReconConfig, bg: BackgroundConfig) -> dict:
    """What determines the stage's output: code version, configs, dataset folder, video id, frame ids and the
    content of the video's frames and cameras."""
    return {"stage": STAGE, "code_version": CODE_VERSION, "video_id": video.video_id,
            "content": video_content_hash(video),
            "dataset": os.path.abspath(video._root),  # noqa: SLF001 (Video has no public root)
            "frame_ids": hash_json(list(video.frame_ids)), "size": [video.width, video.height],
            "recon": to_dict(cfg), "background": to_dict(bg)}


def run_recon_stage(video: Video, cache: StageCache, cfg: ReconConfig, bg: BackgroundConfig,
                    progress: bool = True) -> Path:
    """Build (or reuse, if its key matches) the recon stage of ``video``; returns its folder."""
    import cv2

    key = recon_key(video, cfg, bg)
    if cache.is_valid(STAGE, video.video_id, key):
        return cache.path(STAGE, video.video_id)
    t_start = time.perf_counter()
    recon = reconstruct(video, cfg, progress=progress)
    where = f"video {video.video_id}"
    t0 = time.perf_counter()
    tracked = sorted(recon.T_world_cam)
    up = up_hint_from_poses(np.stack([recon.T_world_cam[f] for f in tracked]))
    keep, plane = remove_support_plane(recon.points_w, recon.normals_w, bg, up_hint=up, where=where)
    t_background = time.perf_counter() - t0
    obj = recon.points_w[keep]

    with cache.write(STAGE, video.video_id, key) as tmp:
        np.savez_compressed(tmp / CLOUD_NPZ, points_w=obj, colors=recon.colors[keep],
                            normals_w=recon.normals_w[keep])
        failures = set(recon.tracking_failures)
        T_all = np.stack([recon.T_world_cam.get(f, np.full((4, 4), np.nan)) for f in video.frame_ids])
        ok = np.array([f in recon.T_world_cam and f not in failures for f in video.frame_ids])
        np.savez_compressed(tmp / POSES_NPZ, frame_ids=np.asarray(video.frame_ids, np.int64),
                            T_world_cam=T_all, tracking_ok=ok)
        write_json(tmp / PLANE_JSON, {"plane": plane.tolist(), "up_hint": up.tolist()})
        vol = recon.volume
        save_grid(vol.vbg, tmp / TSDF_NPZ)
        write_json(tmp / VOLUME_JSON, {"voxel_size_m": vol.voxel_size_m, "block_resolution": vol.block_resolution,
                                       "trunc_m": vol.trunc_m, "K": vol.K.tolist()})
        np.savez_compressed(tmp / KEYFRAMES_NPZ, frame_ids=np.asarray(vol.keyframe_ids, np.int64),
                            T_world_cam=vol.keyframe_T_world_cam, depth_m=vol.keyframe_depth_m)
        t0 = time.perf_counter()
        (tmp / FG_PNG).parent.mkdir()
        fg_pixels = []
        for fid in tqdm(video.frame_ids, desc=f"masks {video.video_id}", disable=not progress, leave=False):
            if fid in recon.T_world_cam:
                depth, K, T = video.depth_m(fid), video.K(fid), recon.T_world_cam[fid]
                mask = foreground_mask(obj, K, T, video.width, video.height, depth_m=depth,
                                       depth_tol_m=bg.mask_depth_tol_m, splat_px=bg.mask_splat_px)
                mask &= ~plane_pixels(depth, K, T, plane, bg.mask_plane_margin_m)  # splats spilt onto the table
            else:
                mask = np.zeros((video.height, video.width), bool)
            fg_pixels.append(int(mask.sum()))
            cv2.imwrite(str(tmp / FG_PNG.format(frame_id=fid)), mask.astype(np.uint8) * 255)
        t_masks = time.perf_counter() - t0
        write_json(tmp / REPORT_JSON, {
            "video_id": video.video_id, "world_frame": "dataset" if cfg.use_gt_poses else "first_camera",
            "frames": len(video.frame_ids), "tracking_failures": recon.tracking_failures,
            "points_fused": int(len(recon.points_w)), "points_kept": int(keep.sum()),
            "plane": plane.tolist(), "fg_pixels_mean": float(np.mean(fg_pixels)),
            "timings_s": {**recon.timings_s, "background_s": round(t_background, 3), "masks_s": round(t_masks, 3),
                          "total_s": round(time.perf_counter() - t_start, 3)}})
    return cache.path(STAGE, video.video_id)


@dataclass
class ReconStage:
    """A loaded recon stage (see the module docstring for the files)."""

    dir: Path
    points_w: np.ndarray
    colors: np.ndarray
    normals_w: np.ndarray
    frame_ids: list[int]
    T_world_cam: dict[int, np.ndarray]  # frames with a pose
    tracking_ok: dict[int, bool]
    plane: np.ndarray
    report: dict
    _volume: Volume | None = field(default=None, repr=False)

    def fg_mask(self, frame_id: int) -> np.ndarray:
        """bool H×W projected foreground mask of a frame."""
        import cv2

        p = self.dir / FG_PNG.format(frame_id=frame_id)
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise FileNotFoundError(f"{p}: missing or unreadable foreground mask")
        return img > 127

    def volume(self) -> Volume:
        """The fused TSDF and keyframes (loaded on first use)."""
        if self._volume is None:
            meta = read_json(self.dir / VOLUME_JSON)
            kf = np.load(self.dir / KEYFRAMES_NPZ)
            vbg = load_grid(self.dir / TSDF_NPZ)
            self._volume = Volume(vbg, meta["voxel_size_m"], meta["block_resolution"], meta["trunc_m"],
                                  np.asarray(meta["K"]), kf["frame_ids"].tolist(), kf["T_world_cam"], kf["depth_m"])
        return self._volume

    def occupancy(self, points_w: np.ndarray) -> np.ndarray:
        """int8 per world point: −1 observed free, 0 unknown, 1 at/behind a surface (see :func:`occupancy`)."""
        return occupancy(self.volume(), points_w)


def save_grid(vbg, path: Path) -> None:
    """Write an open3d VoxelBlockGrid to ``path`` as its own ``save()`` arrays, zip-compressed, blocks in
    lexicographic order of their coordinates (the hash map's order depends on thread scheduling, so the same
    grid would otherwise give different files)."""
    with tempfile.TemporaryDirectory(prefix="selfseg_tsdf_") as d:
        vbg.save(os.path.join(d, TSDF_NPZ))
        with np.load(os.path.join(d, TSDF_NPZ)) as z:
            arrays = {k: z[k] for k in z.files}
    order = np.lexsort(arrays["key"].T[::-1])  # last key is primary: block x, then y, z
    n = len(order)
    np.savez_compressed(path, **{k: v[order] if k == "key" or (k.startswith("value_") and len(v) == n) else v
                                 for k, v in arrays.items()})


def load_grid(path: Path):
    """The VoxelBlockGrid :func:`save_grid` wrote (an uncompressed ``save()`` file is read too)."""
    import open3d as o3d

    with tempfile.TemporaryDirectory(prefix="selfseg_tsdf_") as d, np.load(path) as z:
        plain = os.path.join(d, TSDF_NPZ)
        np.savez(plain, **{k: z[k] for k in z.files})
        return o3d.t.geometry.VoxelBlockGrid.load(plain)


def load_recon(stage_dir: str | Path) -> ReconStage:
    """Read a recon stage folder written by :func:`run_recon_stage`."""
    d = Path(stage_dir)
    if not (d / STAGE_FILE).is_file():
        raise FileNotFoundError(f"{d}: not a completed recon stage (no {STAGE_FILE})")
    cloud = np.load(d / CLOUD_NPZ)
    poses = np.load(d / POSES_NPZ)
    fids = poses["frame_ids"].tolist()
    T = {f: poses["T_world_cam"][i] for i, f in enumerate(fids) if np.isfinite(poses["T_world_cam"][i]).all()}
    ok = {f: bool(poses["tracking_ok"][i]) for i, f in enumerate(fids)}
    return ReconStage(d, cloud["points_w"], cloud["colors"], cloud["normals_w"], fids, T, ok,
                      np.asarray(read_json(d / PLANE_JSON)["plane"]), read_json(d / REPORT_JSON))
