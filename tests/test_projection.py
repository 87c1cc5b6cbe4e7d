"""Z-buffer projection against exact ray casting of analytic scenes."""
from __future__ import annotations

import numpy as np
import trimesh

from selfseg.analytic import box, cylinder
from selfseg.method.projection import foreground_mask, project_labels, zbuffer
from selfseg.raycast import RaycastScene, look_at

W, H, FX = 160, 120, 150.0
K = np.array([[FX, 0, W / 2 - 0.5], [0, FX, H / 2 - 0.5], [0, 0, 1.0]])


def _surface_points(meshes, labels, per_m2=300_000):
    """Points sampled uniformly on the mesh surfaces (deterministic), with one label per mesh."""
    pts, lab = [], []
    for m, l in zip(meshes, labels):
        n = int(m.area * per_m2)
        p, _ = trimesh.sample.sample_surface(m, n, seed=7)
        pts.append(p)
        lab.append(np.full(n, l))
    return np.concatenate(pts), np.concatenate(lab)


def test_single_point_lands_on_its_pixel():
    T = look_at([0, -0.5, 0.3], [0, 0, 0])
    K_odd = K.copy()
    K_odd[0, 2] += 3.25  # an off-centre principal point must be honoured exactly
    # the ray through pixel (u, v) = (100, 30), at depth 0.4
    x_cam = np.array([(100 - K_odd[0, 2]) / FX * 0.4, (30 - K_odd[1, 2]) / FX * 0.4, 0.4])
    p_w = T[:3, :3] @ x_cam + T[:3, 3]
    depth, index = zbuffer(p_w[None], K_odd, T, W, H, splat_px=0)
    assert index[30, 100] == 0 and (index >= 0).sum() == 1
    assert abs(depth[30, 100] - 0.4) < 1e-6
    labels = project_labels(p_w[None], np.array([5]), K_odd, T, W, H, splat_px=1)
    assert (labels == 5).sum() == 9 and labels[29:32, 99:102].min() == 5


def test_projection_matches_raycast_instances():
    meshes = [box((0.08, 0.08, 0.08), (-0.06, 0.0, 0.04)), cylinder(0.04, 0.1, (0.07, 0.03, 0.05))]
    table = box((0.8, 0.8, 0.02), (0, 0, -0.01))
    scene = RaycastScene.from_meshes(meshes + [table], ids=[1, 2, 3])
    pts, lab = _surface_points(meshes, [1, 2])
    for eye in ([0.5, -0.3, 0.35], [-0.2, 0.55, 0.4]):
        T = look_at(eye, [0, 0, 0.04])
        depth, inst, _ = scene.render(K, T, W, H)
        gt = np.where((inst == 1) | (inst == 2), inst.astype(np.int32), -1)  # table and misses: no label
        pred = project_labels(pts, lab, K, T, W, H, depth_m=depth, depth_tol_m=0.01, splat_px=1)
        labelled = gt >= 0
        agreement = (pred[labelled] == gt[labelled]).mean()
        spill = (pred[~labelled] >= 0).mean()
        assert agreement > 0.95, agreement
        assert spill < 0.01, spill
        fg = foreground_mask(pts, K, T, W, H, depth_m=depth)
        np.testing.assert_array_equal(fg, pred >= 0)


def test_depth_test_stops_occluded_points_leaking():
    """An occluder that is not in the cloud hides a labelled box: only the depth test removes it."""
    target = box((0.08, 0.08, 0.08), (0.0, 0.1, 0.04))
    occluder = box((0.06, 0.03, 0.12), (-0.03, -0.05, 0.06))  # hides the target's left half
    table = box((0.8, 0.8, 0.02), (0, 0, -0.01))
    scene = RaycastScene.from_meshes([target, occluder, table], ids=[1, 2, 3])
    T = look_at([0.0, -0.6, 0.15], [0, 0.1, 0.04])
    depth, inst, _ = scene.render(K, T, W, H)
    occluder_px = inst == 2
    assert occluder_px.sum() > 300
    pts, lab = _surface_points([target], [1])
    leaky = project_labels(pts, lab, K, T, W, H, depth_m=None)
    tested = project_labels(pts, lab, K, T, W, H, depth_m=depth)
    assert (leaky[occluder_px] == 1).mean() > 0.3  # the target lies behind the occluder
    assert (tested[occluder_px] >= 0).mean() < 0.01
    visible = inst == 1
    assert (tested[visible] == 1).mean() > 0.95
