"""Analytic scenes for the tests and the benchmarks: trimesh shapes on a table, rendered by ray casting, no Blender.

:func:`make_dataset` writes small datasets in the real dataset format (through :class:`selfseg.writers.VideoWriter`),
so tests exercise the same readers as generated data. :func:`fused_cloud` gives fused-looking point clouds for the
over-segmentation: the meshes (on a table, top at z = 0) ray-cast from cameras all around, the depth back-projected
with ≈1 mm noise, one point per ``grid_m`` cell kept (like a TSDF surface at that voxel size) and the table
dropped (z < ``table_cut_m``); only visible surfaces appear, as in a real reconstruction. :func:`scene_meshes` is
the 9-object tabletop of the over-segmentation benchmarks.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from selfseg.raycast import RaycastScene, backproject, look_at
from selfseg.writers import VideoWriter, write_dataset_info

TABLE_ID = 65535  # internal id of the table in the ray-cast scene; written as 0 (background)
CLOUD_TABLE_ID = 999  # the table's id in fused_cloud's ray-cast scene


def box(size, center) -> trimesh.Trimesh:
    """Axis-aligned box (m) resting at ``center``."""
    m = trimesh.creation.box(extents=size)
    m.apply_translation(center)
    return m


def cylinder(radius, height, center) -> trimesh.Trimesh:
    m = trimesh.creation.cylinder(radius=radius, height=height, sections=48)
    m.apply_translation(center)
    return m


def bowl(radius=0.07, height=0.05, thickness=0.006, center=(0, 0, 0)) -> trimesh.Trimesh:
    """Open bowl: a revolved profile of a thin wall (outer and inner surface), base at z = 0."""
    n = 12
    t = np.linspace(0, np.pi / 2, n)
    outer = np.stack([radius * np.sin(t), height * (1 - np.cos(t))], 1)
    inner = np.stack([(radius - thickness) * np.sin(t[::-1]), height * (1 - np.cos(t[::-1])) + thickness], 1)
    profile = np.concatenate([outer, inner])
    m = trimesh.creation.revolve(profile, sections=48)
    m.apply_translation(center)
    return m


def orbit_cameras(n_frames: int, radius=0.6, height=0.45, target=(0, 0, 0.04), arc_deg=60.0, start_deg=0.0):
    """Camera poses T_world_cam on an arc around ``target`` (≤ 2° per frame by default spacing)."""
    angles = np.deg2rad(start_deg + np.linspace(0, arc_deg, n_frames, endpoint=False))
    return [look_at([radius * np.cos(a), radius * np.sin(a), height], target) for a in angles]


def shade(normals_cam: np.ndarray, inst: np.ndarray, colors: dict[int, tuple[int, int, int]]) -> np.ndarray:
    """Lambertian shading under a head light, in per-instance flat colours (uint8 RGB)."""
    lam = np.clip(-normals_cam[..., 2], 0.2, 1.0)[..., None]
    base = np.zeros(inst.shape + (3,), np.float64)
    for k, c in colors.items():
        base[inst == k] = c
    return np.clip(base * lam, 0, 255).astype(np.uint8)


def write_scene(video_dir: Path, objects: list[tuple[trimesh.Trimesh, int]], cams: list[np.ndarray],
                K: np.ndarray, width: int, height: int, table_size=0.8) -> None:
    """Render one video. objects: (mesh already in world coordinates, obj_id); instance k = index + 1."""
    table = box((table_size, table_size, 0.02), (0, 0, -0.01))
    meshes = [m for m, _ in objects] + [table]
    ids = list(range(1, len(objects) + 1)) + [TABLE_ID]
    scene = RaycastScene.from_meshes(meshes, ids=ids)
    rng = np.random.default_rng(len(objects))
    colors = {k: tuple(int(c) for c in rng.integers(40, 255, 3)) for k in ids[:-1]}
    colors[TABLE_ID] = (200, 190, 170)
    w = VideoWriter(video_dir)
    for fid, T in enumerate(cams):
        depth, inst, normals = scene.render(K, T, width, height)
        rgb = shade(normals, inst, colors)
        inst_out = np.where(inst == TABLE_ID, 0, inst).astype(np.uint16)
        T_cam_world = np.linalg.inv(T)
        objs = [{"obj_id": oid, "inst_id": i + 1, "T_cam_model": T_cam_world} for i, (_, oid) in enumerate(objects)]
        w.write_frame(fid, rgb, depth, inst_out, K, T, objs)
    w.finish({"instances": {str(i + 1): oid for i, (_, oid) in enumerate(objects)},
              "table_plane": [0.0, 0.0, 1.0, 0.0], "seed": 0})


def make_dataset(root: Path, scenes: list[list[tuple[trimesh.Trimesh, int]]], n_frames=6, width=160, height=120,
                 fx=150.0, arc_deg=60.0, name="analytic") -> Path:
    """Write an analytic dataset: each scene is a list of (world-placed mesh, obj_id); models are not written."""
    root = Path(root)
    K = np.array([[fx, 0, width / 2 - 0.5], [0, fx, height / 2 - 0.5], [0, 0, 1.0]])
    for i, objects in enumerate(scenes):
        cams = orbit_cameras(n_frames, arc_deg=arc_deg, start_deg=37.0 * i)
        write_scene(root / "videos" / f"{i:06d}", objects, cams, K, width, height)
    obj_ids = sorted({oid for objs in scenes for _, oid in objs})
    write_dataset_info(root, {"name": name, "generator_version": "tests.analytic", "resolution": [width, height],
                              "seed": 0, "config": {}, "objects": [{"obj_id": o, "name": f"obj{o}"} for o in obj_ids]})
    return root


def two_box_scenes() -> list[list[tuple[trimesh.Trimesh, int]]]:
    """Three scenes with the same two boxes (obj 1, 2) and a cylinder (obj 3) in different places."""
    return [
        [(box((0.08, 0.08, 0.08), (-0.08, 0.0, 0.04)), 1), (box((0.06, 0.1, 0.05), (0.08, 0.02, 0.025)), 2)],
        [(box((0.08, 0.08, 0.08), (0.06, -0.06, 0.04)), 1), (cylinder(0.04, 0.1, (-0.07, 0.05, 0.05)), 3)],
        [(box((0.06, 0.1, 0.05), (0.0, 0.1, 0.025)), 2), (cylinder(0.04, 0.1, (0.0, -0.08, 0.05)), 3),
         (box((0.08, 0.08, 0.08), (-0.12, -0.02, 0.04)), 1)],
    ]


def fused_cloud(meshes, n_views=16, grid_m=0.004, noise_m=0.001, table_cut_m=0.004, seed=0,
                radius=0.5, heights=(0.25, 0.5), width=240, height=180, fx=220.0):
    """(points N×3 m, outward normals N×3, mesh index N (0-based)) of the visible object surfaces."""
    rng = np.random.default_rng(seed)
    table = box((1.0, 1.0, 0.02), (0, 0, -0.01))
    scene = RaycastScene.from_meshes(list(meshes) + [table], ids=list(range(1, len(meshes) + 1)) + [CLOUD_TABLE_ID])
    K = np.array([[fx, 0, width / 2 - 0.5], [0, fx, height / 2 - 0.5], [0, 0, 1.0]])
    target = np.mean([m.bounds.mean(0) for m in meshes], axis=0)
    P, N, L = [], [], []
    for h in heights:
        for a in np.linspace(0, 2 * np.pi, n_views, endpoint=False) + h:
            T = look_at([target[0] + radius * np.cos(a), target[1] + radius * np.sin(a), h], target)
            depth, inst, nrm = scene.render(K, T, width, height)
            depth = np.where(depth > 0, depth + rng.normal(0, noise_m, depth.shape), 0).astype(np.float32)
            pts, vu = backproject(depth, K, (inst > 0) & (inst != CLOUD_TABLE_ID))
            P.append(pts @ T[:3, :3].T + T[:3, 3])
            N.append(nrm[vu[:, 0], vu[:, 1]] @ T[:3, :3].T)
            L.append(inst[vu[:, 0], vu[:, 1]].astype(np.int64) - 1)
    P, N, L = np.concatenate(P), np.concatenate(N), np.concatenate(L)
    _, first = np.unique(np.floor(P / grid_m).astype(np.int64), axis=0, return_index=True)
    P, N, L = P[first], N[first], L[first]
    keep = P[:, 2] > table_cut_m
    return P[keep], N[keep], L[keep]


def scene_meshes() -> list[trimesh.Trimesh]:
    """Nine objects on a table (boxes, cylinders, bowls, a mug with its handle), some touching."""
    handle = trimesh.creation.torus(0.025, 0.006)
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    handle.apply_translation((0.2 + 0.04, -0.15, 0.05))
    return [box((0.08, 0.08, 0.08), (-0.2, -0.15, 0.04)), box((0.06, 0.05, 0.04), (-0.13, -0.15, 0.02)),
            cylinder(0.035, 0.12, (0.0, -0.15, 0.06)), bowl(0.08, 0.05, 0.006, (0.0, 0.05, 0.0)),
            cylinder(0.02, 0.1, (0.0, 0.05, 0.056)), box((0.12, 0.04, 0.03), (-0.22, 0.08, 0.015)),
            box((0.05, 0.06, 0.1), (-0.135, 0.08, 0.05)),
            trimesh.util.concatenate([cylinder(0.035, 0.09, (0.2, -0.15, 0.045)), handle]),
            bowl(0.06, 0.04, 0.005, (0.2, 0.12, 0.0))]
