"""Exact depth and instance rendering of triangle meshes by ray casting (open3d), no Blender.

Used to check the generator's ground truth against the stored models and poses, to label
reconstructed points by their nearest object surface, and to build small analytic test scenes.
Units: metres; ``K`` in the OpenCV pixel-centre convention (see :mod:`selfseg.dataset`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selfseg.poses import transform_points


@dataclass
class RaycastScene:
    """Meshes placed in the world, each tagged with an integer id (instance id, ≥ 1)."""

    vertices: list[np.ndarray]  # per mesh, V×3 world coordinates (m)
    faces: list[np.ndarray]  # per mesh, F×3
    ids: list[int]

    @classmethod
    def from_meshes(cls, meshes: list, poses: list[np.ndarray] | None = None, ids: list[int] | None = None) -> "RaycastScene":
        """meshes: trimesh-like objects with .vertices (m, model frame) and .faces; poses: T_world_model."""
        verts, faces = [], []
        for i, m in enumerate(meshes):
            v = np.asarray(m.vertices, dtype=np.float64)
            if poses is not None:
                v = transform_points(v, poses[i])
            verts.append(v)
            faces.append(np.asarray(m.faces, dtype=np.int64))
        return cls(verts, faces, list(ids) if ids is not None else list(range(1, len(meshes) + 1)))

    def _o3d_scene(self):
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        geom_ids = []
        for v, f in zip(self.vertices, self.faces):
            geom_ids.append(scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)),
                                                o3d.core.Tensor(f.astype(np.uint32))))
        return scene, np.asarray(geom_ids)

    def render(self, K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int):
        """Planar depth (m, 0 = miss), instance ids (uint16, 0 = miss) and unit normals in the camera frame."""
        import open3d as o3d

        scene, geom_ids = self._o3d_scene()
        u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)  # z = 1
        R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
        d_world = d_cam @ R.T
        rays = np.concatenate([np.broadcast_to(t, d_world.shape), d_world], -1).astype(np.float32)
        ans = scene.cast_rays(o3d.core.Tensor(rays))
        t_hit = ans["t_hit"].numpy()  # in units of the ray direction, whose z component is 1: planar depth
        hit = np.isfinite(t_hit)
        depth = np.where(hit, t_hit, 0).astype(np.float32)
        gid = ans["geometry_ids"].numpy().astype(np.int64)
        id_of_geom = np.zeros(int(geom_ids.max()) + 2 if len(geom_ids) else 1, dtype=np.int64)
        id_of_geom[geom_ids] = self.ids
        inst = np.where(hit, id_of_geom[np.where(hit, gid, 0)], 0).astype(np.uint16)
        normals_cam = ans["primitive_normals"].numpy() @ R  # world → camera: n_cam = R^T n_world
        return depth, inst, normals_cam.astype(np.float32)

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance (m) to the nearest mesh surface and that mesh's id, for each world point (N×3, m)."""
        import open3d as o3d

        points = np.asarray(points, dtype=np.float64)
        scene, geom_ids = self._o3d_scene()
        ans = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
        gid = ans["geometry_ids"].numpy().astype(np.int64)
        id_of_geom = np.zeros(int(geom_ids.max()) + 2, dtype=np.int64)
        id_of_geom[geom_ids] = self.ids
        return np.linalg.norm(ans["points"].numpy() - points, axis=1), id_of_geom[gid]

    def nearest_id(self, points: np.ndarray, max_dist_m: float) -> np.ndarray:
        """Id of the nearest mesh surface for each world point, or 0 if farther than ``max_dist_m``."""
        dist, ids = self.closest(points)
        return np.where(dist <= max_dist_m, ids, 0)


def backproject(depth_m: np.ndarray, K: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pixels with depth > 0 (and inside ``mask``) → camera-frame points (N×3, m) and their (v, u) indices."""
    valid = depth_m > 0
    if mask is not None:
        valid &= mask.astype(bool)
    v, u = np.nonzero(valid)
    z = depth_m[v, u].astype(np.float64)
    pts = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
    return pts, np.stack([v, u], -1)


def xyz_map(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Organised point map: depth (m, H×W) → camera-frame XYZ H×W×3 float32 (m), zeros where depth is 0."""
    h, w = depth_m.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    z = depth_m.astype(np.float32)
    return np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1).astype(np.float32)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """T_world_cam of an OpenCV camera at ``eye`` looking at ``target`` (world z up)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking straight down: pick any perpendicular x
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = eye
    return T
