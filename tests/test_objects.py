"""Object library: builtin objects, textures, user meshes and the models written into a dataset."""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from PIL import Image

from selfseg.dataset import MODEL_PLY, MODELS_INFO
from selfseg.generate.objects import (PAPER_SUBSET, ObjectLibraryError, builtin_library, load_user_objects,
                                      write_models)
from selfseg.generate.textures import PATTERNS, make_texture, table_texture


@pytest.fixture(scope="module")
def library():
    return builtin_library()


@pytest.fixture(scope="module")
def by_name(library):
    return {o.name: o for o in library}


def test_library_has_the_required_objects(library, by_name):
    names = [o.name for o in library]
    assert len(names) >= 24 and len(set(names)) == len(names)
    assert sum(o.nonconvex for o in library) >= 8
    for required in ("lamp", "dumbbell", "mug", "bowl", "bottle", "pitcher", "duck", "hammer", "drill", "banana",
                     "ball", "can_soda", "box_small", "box_large"):
        assert required in by_name
    for name in ("lamp", "dumbbell", "mug", "bowl", "bottle", "pitcher", "duck", "hammer", "banana"):
        assert by_name[name].nonconvex
    assert len(by_name["lamp"].part_names) == 3  # base, gooseneck, shade
    assert by_name["duck"].source == "pybullet_data:duck.obj"
    assert len(PAPER_SUBSET) == 17 and len(set(PAPER_SUBSET)) == 17 and set(PAPER_SUBSET) <= set(names)


def test_library_is_deterministic(library):
    again = builtin_library()
    assert [o.name for o in again] == [o.name for o in library]
    for a, b in zip(library, again):
        assert np.array_equal(a.texture, b.texture) and np.array_equal(a.vertices, b.vertices)
        assert np.array_equal(a.uv, b.uv) and np.array_equal(a.faces, b.faces)


def test_textures_are_distinct(library):
    small = [np.asarray(Image.fromarray(o.texture).resize((32, 32)), dtype=np.float64) for o in library]
    for i in range(len(small)):
        for j in range(i + 1, len(small)):
            diff = np.abs(small[i] - small[j]).mean()
            assert diff > 20, f"{library[i].name} and {library[j].name} look alike (mean difference {diff:.1f})"


def test_meshes_are_valid(library):
    for o in library:
        assert o.vertices.dtype == np.float64 and o.faces.dtype == np.int64 and o.uv.shape == (len(o.vertices), 2)
        assert o.faces.min() == 0 and o.faces.max() == len(o.vertices) - 1
        assert np.all(trimesh.triangles.area(o.vertices[o.faces]) > 1e-9), o.name
        assert o.uv.min() >= 0 and o.uv.max() <= 1, o.name
        assert o.texture.dtype == np.uint8 and o.texture.ndim == 3 and o.texture.shape[2] == 3
        merged = trimesh.Trimesh(o.vertices, o.faces)  # seams merged by position
        assert merged.is_watertight and merged.volume > 0, f"{o.name}: not a closed outward surface"
        ext = merged.extents
        assert 0.02 <= ext.max() <= 0.26 and ext.min() >= 0.02, f"{o.name}: {ext} m"
        lo, hi = merged.bounds  # model origin at the bottom centre
        assert lo[2] == pytest.approx(0.0, abs=1e-9) and np.allclose((lo + hi)[:2] / 2, 0.0, atol=1e-9)


def test_collision_parts_fit_the_nonconvex_meshes(library):
    for o in library:
        if not o.nonconvex:
            assert o.collision_parts is None
            continue
        mesh = trimesh.Trimesh(o.vertices, o.faces)
        assert mesh.volume < 0.95 * mesh.convex_hull.volume, f"{o.name} is not really non-convex"
        assert len(o.collision_parts) >= 2, o.name
        pts = np.vstack([v for v, _ in o.collision_parts])
        assert np.allclose(pts.min(0), o.vertices.min(0), atol=1e-3) and np.allclose(pts.max(0), o.vertices.max(0),
                                                                                      atol=1e-3), o.name
        parts_volume = sum(trimesh.Trimesh(v, f).volume for v, f in o.collision_parts)
        assert parts_volume < 1.4 * mesh.volume, f"{o.name}: the convex pieces fill its concavities"


def test_vertex_colors_follow_the_uv_convention(by_name):
    o = by_name["can_soda"]
    ref = trimesh.visual.color.uv_to_color(o.uv, Image.fromarray(o.texture))[:, :3]
    assert np.array_equal(o.vertex_colors(), ref)


def test_make_texture():
    a = make_texture("checks", ("red", "white"), 3, (64, 48))
    assert a.shape == (64, 48, 3) and a.dtype == np.uint8
    assert np.array_equal(a, make_texture("checks", ("red", "white"), 3, (64, 48)))
    assert not np.array_equal(a, make_texture("checks", ("red", "white"), 4, (64, 48)))
    for p in PATTERNS:
        assert make_texture(p, ("blue", "yellow"), 0, (32, 32), text="AB").shape == (32, 32, 3)
    with pytest.raises(ValueError, match="unknown texture pattern"):
        make_texture("zigzag", ("red",), 0)
    t = table_texture(7, (40, 50))
    assert t.shape == (40, 50, 3) and np.array_equal(t, table_texture(7, (40, 50)))


def test_write_models_in_millimetres(tmp_path, by_name):
    objs = [by_name["cube"], by_name["mug"], by_name["duck"]]
    write_models(tmp_path, objs)
    info = json.loads((tmp_path / MODELS_INFO).read_text())
    assert sorted(info) == ["1", "2", "3"]
    for i, o in enumerate(objs):
        ply = trimesh.load(tmp_path / MODEL_PLY.format(obj_id=i + 1), process=False)
        assert ply.vertices.shape == o.vertices.shape and len(ply.faces) == len(o.faces)
        assert np.allclose(ply.bounds, trimesh.Trimesh(o.vertices, o.faces, process=False).bounds * 1000, atol=1e-3)
        assert np.array_equal(np.asarray(ply.visual.vertex_colors)[:, :3], o.vertex_colors())
        rec = info[str(i + 1)]
        assert rec["name"] == o.name
        mm = o.vertices * 1000
        assert rec["diameter"] == pytest.approx(np.sqrt(((mm[:, None] - mm[None]) ** 2).sum(-1).max()), rel=1e-9)
        assert [rec["min_x"], rec["min_y"], rec["min_z"]] == pytest.approx(mm.min(0).tolist())
        assert [rec["size_x"], rec["size_y"], rec["size_z"]] == pytest.approx((mm.max(0) - mm.min(0)).tolist())
    assert info["1"]["diameter"] == pytest.approx(60 * np.sqrt(3))  # the 6 cm cube
    assert not list(tmp_path.rglob("*.tmp"))


def _textured_box(size: float) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(size, size / 2, size / 3))
    rng = np.random.default_rng(0)
    tex = Image.fromarray(rng.integers(0, 255, (16, 16, 3), dtype=np.uint8))
    uv = np.clip((box.vertices[:, :2] / size) + 0.5, 0, 1)
    box.visual = trimesh.visual.TextureVisuals(uv=uv, image=tex)
    return box


def test_load_user_objects(tmp_path):
    box = _textured_box(0.1)
    box.export(tmp_path / "boxy.obj")  # writes boxy.obj, material.mtl, material_0.png
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.04)
    sphere.visual.vertex_colors = np.tile([10, 200, 30, 255], (len(sphere.vertices), 1))
    (tmp_path / "ball" / "google_16k").mkdir(parents=True)
    sphere.export(tmp_path / "ball" / "google_16k" / "textured.ply")
    trimesh.creation.box(extents=(0.5, 0.5, 0.5)).export(tmp_path / "ball" / "google_16k" / "nontextured.ply")
    (tmp_path / "notes.txt").write_text("ignored")
    objs = load_user_objects(tmp_path)
    assert [o.name for o in objs] == ["ball", "boxy"]
    ball, boxy = objs
    assert np.allclose(trimesh.Trimesh(ball.vertices, ball.faces).extents, 0.08, atol=1e-6)  # textured.ply chosen
    assert np.all(ball.vertex_colors() == [10, 200, 30])
    assert boxy.source.startswith("user:") and boxy.source.endswith("boxy.obj")
    assert np.allclose(trimesh.Trimesh(boxy.vertices, boxy.faces).extents, [0.1, 0.05, 0.1 / 3])
    assert boxy.texture.shape == (16, 16, 3) and np.array_equal(boxy.vertex_colors(), boxy.trimesh().visual.to_color()
                                                                .vertex_colors[:, :3])
    assert not boxy.nonconvex and not ball.nonconvex and boxy.uv.min() >= 0 and boxy.uv.max() <= 1


def test_load_user_objects_errors(tmp_path):
    with pytest.raises(ObjectLibraryError, match="does not exist"):
        load_user_objects(tmp_path / "nope")
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "readme.md").write_text("no meshes here")
    with pytest.raises(ObjectLibraryError, match="no meshes found"):
        load_user_objects(empty)
    sub = tmp_path / "sub"
    (sub / "thing").mkdir(parents=True)
    with pytest.raises(ObjectLibraryError, match="thing: object folder contains no mesh"):
        load_user_objects(sub)
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "broken.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n")
    with pytest.raises(ObjectLibraryError, match="broken.ply: unreadable mesh"):
        load_user_objects(bad)
    mm = tmp_path / "mm"
    mm.mkdir()
    trimesh.creation.box(extents=(100, 50, 30)).export(mm / "big.ply")
    with pytest.raises(ObjectLibraryError, match="big.ply: .*metres"):
        load_user_objects(mm)


def test_paper_library_is_chunky_multipart_and_distinct():
    """The `paper` toys: 6–20 cm, several convex parts each ≥ ~2 cm thick, one texture per part."""
    from selfseg.generate.objects import paper_library

    toys = paper_library()
    names = [o.name for o in toys]
    assert len(names) == len(set(names)) >= 12 and not set(names) & (set(o.name for o in builtin_library()) - {"duck"})
    for o in toys:
        size_cm = (o.vertices.max(0) - o.vertices.min(0)).max() * 100
        assert 6 <= size_cm <= 20.5, f"{o.name}: {size_cm:.1f} cm"
        assert o.nonconvex and o.collision_parts
        if o.name != "duck":
            assert len(o.part_names) >= 2, o.name
            for v, _ in o.collision_parts:  # each convex piece is at least 1.9 cm thick along its thinnest axis
                c = v - v.mean(0)
                axis = np.linalg.eigh(c.T @ c)[1][:, 0]
                assert np.ptp(c @ axis) >= 0.019, f"{o.name}: a part {np.ptp(c @ axis) * 100:.1f} cm thin"
    small = [np.asarray(Image.fromarray(o.texture).resize((32, 32)), dtype=np.float64) for o in toys]
    for i in range(len(toys)):
        for j in range(i + 1, len(toys)):
            assert np.abs(small[i] - small[j]).mean() > 20, f"{names[i]} and {names[j]} look alike"
    again = paper_library()
    assert all(np.array_equal(a.vertices, b.vertices) and np.array_equal(a.texture, b.texture)
               for a, b in zip(toys, again))
