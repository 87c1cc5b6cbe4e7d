"""Physics drop: objects come to rest on the table without interpenetrating, deterministically."""
from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh

from selfseg.generate.determinism import pinned_env
from selfseg.generate.objects import ObjectModel, builtin_library
from selfseg.generate.physics import TABLE_ID, PhysicsConfig, collision_body, drop_objects

MM = 1e-3


@pytest.fixture(scope="module")
def lib():
    return {o.name: o for o in builtin_library()}


def _world(obj: ObjectModel, T: np.ndarray) -> np.ndarray:
    return obj.vertices @ T[:3, :3].T + T[:3, 3]


def _penetration(points: np.ndarray, hull_vertices: np.ndarray) -> float:
    """Deepest penetration (m) of ``points`` into the convex hull of ``hull_vertices`` (0 if none inside)."""
    hull = trimesh.convex.convex_hull(hull_vertices)
    # signed distance to every face plane; a point is inside when all are negative
    planes = np.einsum("fk,pk->pf", hull.face_normals, points) - np.einsum("fk,fk->f", hull.face_normals,
                                                                           hull.triangles[:, 0])
    depth = -planes.max(axis=1)  # > 0 inside: distance to the nearest face plane
    return float(max(depth.max(), 0.0))


def _pieces_world(obj: ObjectModel, T: np.ndarray) -> list[np.ndarray]:
    parts = [v for v, _ in obj.collision_parts] if obj.collision_parts is not None else [obj.vertices]
    return [p @ T[:3, :3].T + T[:3, 3] for p in parts]


@pytest.mark.parametrize("name", ["cube", "ball", "mug", "bowl", "duck", "lamp", "banana"])
def test_single_object_rests_on_the_table(lib, name):
    obj = lib[name]
    r = drop_objects([obj], seed=1)
    assert r.removed == [] and list(r.poses) == [0] and r.attempts == 1
    T = r.poses[0]
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6) and np.allclose(T[3], [0, 0, 0, 1])
    lowest = _world(obj, T)[:, 2].min()
    assert abs(lowest) < 3 * MM, f"{name}: lowest point {lowest * 1000:.2f} mm from the table"
    assert r.max_penetration_m < 3 * MM


def test_pile_settles_without_interpenetration(lib):
    names = ["box_medium", "mug", "bottle", "dumbbell", "can_soup", "hammer", "bowl", "cheese_wedge"]
    objs = [lib[n] for n in names]
    r = drop_objects(objs, seed=3, cfg=PhysicsConfig(drop_radius_m=0.07))
    assert len(r.poses) >= 6 and sorted(list(r.poses) + r.removed) == list(range(len(objs)))
    assert r.max_penetration_m < 3 * MM and r.penetrations == {}
    # every kept object is supported: it touches the table or another object, and some touch each other
    touching = {k for pair in r.contacts for k in pair}
    assert set(r.poses) <= touching
    assert any(TABLE_ID not in pair for pair in r.contacts)
    h = PhysicsConfig().table_half_extent_m
    world = {i: _world(objs[i], T) for i, T in r.poses.items()}
    for i, pts in world.items():
        assert pts[:, 2].min() > -3 * MM, f"{names[i]} sinks into the table"
        assert np.abs(r.poses[i][:2, 3]).max() < h
    # an independent check: no object's surface points lie more than 3 mm inside another's convex pieces
    for i in r.poses:
        for j in r.poses:
            if i != j:
                depth = max(_penetration(world[i], piece) for piece in _pieces_world(objs[j], r.poses[j]))
                assert depth < 3 * MM, f"{names[i]} is {depth * 1000:.1f} mm inside {names[j]}"
    # an object resting on others lies above the table
    on_top = [i for i in r.poses if (TABLE_ID, i) not in r.contacts]
    assert all(world[i][:, 2].min() > 5 * MM for i in on_top)


def test_same_seed_same_poses(lib):
    objs = [lib[n] for n in ("cube", "mug", "banana", "jar")]
    a, b = drop_objects(objs, seed=11), drop_objects(objs, seed=11)
    assert a.poses.keys() == b.poses.keys() and a.removed == b.removed and a.steps == b.steps
    for i in a.poses:
        assert np.array_equal(a.poses[i], b.poses[i])
    c = drop_objects(objs, seed=12)
    assert any(not np.allclose(a.poses[i], c.poses[i]) for i in a.poses.keys() & c.poses.keys())


def test_objects_off_a_small_table_are_removed(lib):
    objs = [lib[n] for n in ("cube", "can_soda", "box_small", "jar", "egg", "hex_box")]
    cfg = PhysicsConfig(table_half_extent_m=0.08, drop_radius_m=0.12)  # drops partly beside a 16 cm table
    r = drop_objects(objs, seed=6, cfg=cfg)
    assert r.removed, "objects dropped beside a small table must fall off"
    assert sorted(list(r.poses) + r.removed) == list(range(len(objs))) and not set(r.poses) & set(r.removed)
    for i, T in r.poses.items():
        assert (TABLE_ID, i) in r.contacts
        assert _world(objs[i], T)[:, 2].min() > -3 * MM
    # with min_kept the drop is repeated with new sub-seeds until enough objects stay
    again = drop_objects(objs, seed=6, cfg=cfg, min_kept=len(r.poses) + 1)
    assert again.attempts > 1 and len(again.poses) >= len(r.poses) + 1
    with pytest.raises(RuntimeError, match="fewer than 6 of 6 objects"):
        drop_objects(objs, seed=5, cfg=PhysicsConfig(table_half_extent_m=0.01, max_attempts=2), min_kept=6)
    with pytest.raises(ValueError, match="min_kept"):
        drop_objects(objs, seed=5, min_kept=7)


def _l_shape() -> ObjectModel:
    """An L of two 3 cm bars (non-convex, no parts given): physics must decompose it with VHACD."""
    a = trimesh.creation.box((0.1, 0.03, 0.03))
    b = trimesh.creation.box((0.03, 0.03, 0.08))
    b.apply_translation((0.035, 0, 0.04))
    m = trimesh.util.concatenate([a, b])
    m.apply_translation((0, 0, 0.015))
    n = len(m.vertices)
    return ObjectModel("ell", m.vertices, m.faces.astype(np.int64), np.zeros((n, 2)), np.zeros((2, 2, 3), np.uint8),
                       None, True, "test")


def test_vhacd_decomposition_is_cached(tmp_path, monkeypatch):
    ell = _l_shape()
    body = collision_body(ell, PhysicsConfig(vhacd_resolution=20000), tmp_path)
    cached = sorted(tmp_path.glob("vhacd_*.obj"))
    assert len(cached) == 1 and len(body.pieces) >= 2
    # the decomposition keeps the L's notch free: the pieces' volume is far below the convex hull's
    hull_volume = trimesh.Trimesh(ell.vertices, ell.faces).convex_hull.volume
    assert sum(trimesh.convex.convex_hull(v).volume for v, _ in body.pieces) < 0.8 * hull_volume
    stamp = cached[0].stat().st_mtime_ns
    r = drop_objects([ell], seed=0, cfg=PhysicsConfig(vhacd_resolution=20000), cache_dir=tmp_path)
    assert cached[0].stat().st_mtime_ns == stamp  # reused, not recomputed
    assert list(r.poses) == [0] and abs(_world(ell, r.poses[0])[:, 2].min()) < 3 * MM
    # a pinned process (the generate_scenes command) never reads this unpinned process's decomposition
    monkeypatch.setattr(os, "environ", pinned_env(dict(os.environ)))
    collision_body(ell, PhysicsConfig(vhacd_resolution=20000), tmp_path)
    assert [p.name.endswith("_unpinned.obj") for p in sorted(tmp_path.glob("vhacd_*.obj"))] == [False, True]


def test_spread_layout_keeps_objects_apart_and_is_deterministic():
    """layout="spread" starts each object clear of the others: far fewer contacts than a pile of the same objects."""
    from selfseg.generate.objects import paper_library

    toys = paper_library()[:8]
    pile = drop_objects(toys, seed=5, cfg=PhysicsConfig(drop_radius_m=0.15))
    spread_cfg = PhysicsConfig(layout="spread", drop_radius_m=0.25, spread_gap_m=0.01)
    spread = drop_objects(toys, seed=5, cfg=spread_cfg)
    pairs = lambda r: [p for p in r.contacts if TABLE_ID not in p]  # noqa: E731 (object–object contacts)
    assert len(pairs(spread)) < len(pairs(pile)) and len(pairs(pile)) >= 3
    assert len(spread.poses) >= 7 and spread.max_penetration_m < 3 * MM
    again = drop_objects(toys, seed=5, cfg=spread_cfg)
    assert all(np.array_equal(spread.poses[k], again.poses[k]) for k in spread.poses)
    with pytest.raises(ValueError, match="layout"):
        PhysicsConfig(layout="grid")
