"""Support-plane removal on point clouds back-projected from exact ray-cast depth (table top at z = 0)."""
from __future__ import annotations

import numpy as np
import pytest

from selfseg.analytic import box, orbit_cameras
from selfseg.method.background import (BackgroundConfig, BackgroundError, plane_pixels, remove_support_plane,
                                       up_hint_from_poses)
from selfseg.raycast import RaycastScene, backproject, look_at

W, H = 160, 120
K = np.array([[150.0, 0, W / 2 - 0.5], [0, 150.0, H / 2 - 0.5], [0, 0, 1]])
BOX = ((0.08, 0.06, 0.1), (0.05, 0.0, 0.05))  # size, centre: stands on the table


def _scan(meshes, cams):
    """World points and unit normals seen from ``cams`` (ray-cast, exact)."""
    scene = RaycastScene.from_meshes(meshes)
    pts, nrm = [], []
    for T in cams:
        depth, _, n_cam = scene.render(K, T, W, H)
        p, vu = backproject(depth, K)
        pts.append(p @ T[:3, :3].T + T[:3, 3])
        nrm.append(n_cam[vu[:, 0], vu[:, 1]] @ T[:3, :3].T)
    return np.concatenate(pts), np.concatenate(nrm)


@pytest.fixture(scope="module")
def box_on_table():
    cams = orbit_cameras(6, arc_deg=90.0)
    table = box((0.8, 0.8, 0.02), (0, 0, -0.01))
    wall = box((0.02, 1.2, 0.8), (-0.6, 0, 0.2))  # a large vertical plane behind the table
    wall_cams = [look_at([0.0, y, 0.3], [-0.6, y, 0.3]) for y in (-0.3, 0.0, 0.3)]
    pts, nrm = _scan([box(*BOX), table, wall], cams + wall_cams)
    return pts, nrm, np.stack(cams)


def _in_box(pts, margin=0.0):
    size, centre = np.asarray(BOX[0]), np.asarray(BOX[1])
    return np.all(np.abs(pts - centre) <= size / 2 + margin, axis=1)


def test_plane_removed_completely_and_box_kept(box_on_table):
    pts, nrm, cams = box_on_table
    wall = pts[:, 0] < -0.55
    assert wall.sum() > (np.abs(pts[:, 2]) < 1e-3).sum()  # the wall is the largest plane
    up = up_hint_from_poses(cams)
    for normals in (nrm, None):
        keep, plane = remove_support_plane(pts, normals, BackgroundConfig(), up_hint=up)
        np.testing.assert_allclose(plane, [0, 0, 1, 0], atol=2e-3)
        kept = pts[keep]
        assert kept[:, 2].min() > 0.005  # nothing of the table survives, not even its top 5 mm layer
        box_pts = _in_box(pts) & (pts[:, 2] > 0.01)
        assert keep[box_pts].mean() > 0.97
        if normals is not None:  # without normals, the wall's foot widens the table's hull
            assert _in_box(kept, 0.002).all() and not keep[wall].any()


def test_orientation_without_up_hint(box_on_table):
    pts, nrm, _ = box_on_table
    table_and_box = pts[:, 0] > -0.55
    keep, plane = remove_support_plane(pts[table_and_box], None, BackgroundConfig())
    np.testing.assert_allclose(plane, [0, 0, 1, 0], atol=2e-3)  # normal points towards the box
    assert _in_box(pts[table_and_box][keep], 0.002).all()


def test_up_hint_from_orbit_poses():
    up = up_hint_from_poses(np.stack(orbit_cameras(10)))
    assert np.degrees(np.arccos(up @ [0, 0, 1])) < 40  # the cameras look down at ~34°


def test_no_plane_is_a_clear_error():
    rng = np.random.default_rng(0)
    sphere = rng.normal(size=(20000, 3))
    sphere = 0.1 * sphere / np.linalg.norm(sphere, axis=1, keepdims=True)
    with pytest.raises(BackgroundError, match="video 7: no support plane"):
        remove_support_plane(sphere, None, BackgroundConfig(), up_hint=np.array([0, 0, 1.0]), where="video 7")
    with pytest.raises(BackgroundError, match="only 10 points"):
        remove_support_plane(sphere[:10], None, BackgroundConfig(), where="video 7")
    # a horizontal plane exists, but the up hint says it is a wall
    plane = np.c_[rng.uniform(-0.3, 0.3, (5000, 2)), np.zeros(5000)]
    with pytest.raises(BackgroundError, match="tilt 90°"):
        remove_support_plane(plane, None, BackgroundConfig(), up_hint=np.array([1.0, 0, 0]))


def test_plane_pixels_are_the_table():
    table = box((0.8, 0.8, 0.02), (0, 0, -0.01))
    scene = RaycastScene.from_meshes([box(*BOX), table], ids=[1, 2])
    T = orbit_cameras(1)[0]
    depth, inst, _ = scene.render(K, T, W, H)
    on_plane = plane_pixels(depth, K, T, np.array([0, 0, 1.0, 0]), 0.004)
    assert on_plane[inst == 2].all()
    assert on_plane[inst == 1].mean() < 0.05  # only the box's lowest 4 mm
    assert not on_plane[inst == 0].any()  # no measurement: undecided, not background


def test_ransac_plane_is_exact_on_a_noisy_plane_and_repeatable():
    """A 2 mm-noise plane at 30° tilt under a 40 % cloud of clutter: the plane within 1 mrad and 1 mm, its
    inliers, and the same bits on a second call with the same seed (the answer must not depend on threads)."""
    from selfseg.method.background import ransac_plane

    rng = np.random.default_rng(3)
    n_true = np.array([0.0, np.sin(np.radians(30)), np.cos(np.radians(30))])
    u = np.cross(n_true, [1.0, 0, 0])
    uv = rng.uniform(-0.5, 0.5, (6000, 2))
    plane_pts = uv[:, :1] * [1.0, 0, 0] + uv[:, 1:] * u + rng.normal(0, 0.002, (6000, 1)) * n_true + n_true * 0.3
    clutter = rng.uniform(-0.5, 0.5, (4000, 3))
    pts = np.r_[plane_pts, clutter]
    a = ransac_plane(pts, 0.006, 500, np.random.default_rng(0))
    b = ransac_plane(pts, 0.006, 500, np.random.default_rng(0))
    assert a[0].tobytes() == b[0].tobytes() and np.array_equal(a[1], b[1])
    plane, inliers = a
    plane = plane if plane[:3] @ n_true > 0 else -plane
    assert np.degrees(np.arccos(min(1.0, plane[:3] @ n_true))) < np.degrees(1e-3)
    assert abs(plane[3] + 0.3) < 1e-3
    assert (inliers < 6000).mean() > 0.95 and np.isin(np.arange(6000), inliers).mean() > 0.99
