"""The object library: procedural textured rigid objects, the pybullet_data duck, user meshes.

Every object is an :class:`ObjectModel`: a triangle mesh in metres in its own model frame
(z up, origin at the centre of the bottom of its bounding box), per-vertex texture coordinates
into one RGB texture image, and for non-convex objects a decomposition into convex collision
pieces for the physics simulation. Texture coordinates follow the OBJ/OpenGL convention:
v = 0 is the bottom row of the image (the last array row).

Multi-part objects (lamp, mug, ...) are several watertight parts concatenated; each part's
texture occupies its own horizontal band of one texture atlas.

Names, geometry and textures are deterministic: a texture is seeded by the object's name.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from selfseg.dataset import MODEL_PLY, MODELS_INFO
from selfseg.fileio import atomic_write_bytes, write_json
from selfseg.generate.determinism import snap
from selfseg.generate.textures import atlas, make_texture, seed_from_name
from selfseg.poses import transform_points

SECTIONS = 48  # angular resolution of round parts
TEXTURE_SIZE = (256, 256)  # (height, width) of one part's texture
MESH_EXTENSIONS = (".obj", ".ply", ".glb", ".gltf")
# Limits on user meshes, checked when they are loaded (before physics or rendering):
MAX_FACES = 200_000  # more: decimate first (e.g. Blender's Decimate modifier, ratio MAX_FACES / faces)
MAX_EXTENT_M = 0.5  # largest side of a table-top object that the scenes' camera orbit keeps in view
MIN_EXTENT_M = 0.01  # smaller objects cover a few pixels at most
MIN_THICKNESS_M = 0.001  # a mesh thinner than this along every direction of one axis is flat (no volume)


class ObjectLibraryError(ValueError):
    """An object mesh or folder cannot be used; the message names the file and the problem."""


@dataclass
class ObjectModel:
    """A textured rigid object (metres, model frame, z up)."""

    name: str  # stable unique name
    vertices: np.ndarray  # V×3 float64, metres
    faces: np.ndarray  # F×3 int64
    uv: np.ndarray  # V×2 float64 in [0, 1]; v = 0 is the bottom row of `texture`
    texture: np.ndarray  # H×W×3 uint8 RGB
    collision_parts: list[tuple[np.ndarray, np.ndarray]] | None  # convex pieces (V×3, F×3), model frame
    nonconvex: bool
    source: str  # "builtin" | "pybullet_data:duck.obj" | "user:/path/file.obj"
    part_names: list[str] = field(default_factory=list)  # informative: the parts of a multi-part object

    def trimesh(self) -> trimesh.Trimesh:
        """The mesh as a :class:`trimesh.Trimesh` with its texture (not processed: vertices keep their order)."""
        from PIL import Image

        visual = trimesh.visual.TextureVisuals(uv=self.uv, image=Image.fromarray(self.texture))
        return trimesh.Trimesh(vertices=self.vertices, faces=self.faces, visual=visual, process=False)

    def vertex_colors(self) -> np.ndarray:
        """V×3 uint8 RGB colour of the texture at each vertex's UV (nearest texel)."""
        h, w = self.texture.shape[:2]
        uv = np.clip(self.uv, 0.0, 1.0)
        col = np.rint(uv[:, 0] * (w - 1)).astype(np.int64)
        row = np.rint((1.0 - uv[:, 1]) * (h - 1)).astype(np.int64)
        return self.texture[row, col]


# ---- mesh building blocks ------------------------------------------------------------------
@dataclass
class _Part:
    """One watertight textured piece: vertices (m), faces, per-vertex UV, its own texture, convex pieces."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    texture: np.ndarray
    collision: list[np.ndarray]  # point sets whose convex hulls cover the part

    def transformed(self, T: np.ndarray) -> "_Part":
        return _Part(self.name, transform_points(self.vertices, T), self.faces, self.uv, self.texture,
                     [transform_points(c, T) for c in self.collision])


def _compact(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drop unreferenced vertices and renumber faces."""
    used = np.unique(faces)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[faces], uv[used]


def _orient_outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Flip the winding of a closed surface if its signed volume is negative."""
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    vol = np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() / 6.0
    return faces if vol > 0 else faces[:, ::-1].copy()


def _sweep(centres: np.ndarray, radii: np.ndarray, normals: np.ndarray, binormals: np.ndarray,
           sections: int = SECTIONS) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Generalised surface of revolution: ring k is ``centres[k] + radii[k]·(cos θ n_k + sin θ b_k)``.

    The first and last rings must have radius 0 (poles), which closes the surface. Returns
    vertices, faces (outward), UV (u = θ/2π with a duplicated seam column, v = arc length along
    the profile) and the N×(S+1)×3 ring grid (for collision pieces).
    """
    n, s = len(centres), sections
    theta = np.linspace(0.0, 2.0 * np.pi, s + 1)
    ring = (centres[:, None, :] + radii[:, None, None] * (np.cos(theta)[None, :, None] * normals[:, None, :]
                                                          + np.sin(theta)[None, :, None] * binormals[:, None, :]))
    step = np.sqrt((np.diff(centres, axis=0) ** 2).sum(1) + np.diff(radii) ** 2)
    v = np.concatenate([[0.0], np.cumsum(step)]) / step.sum()
    u = np.tile(theta / (2.0 * np.pi), (n, 1))
    pole = radii <= 0
    u[pole, :s] = (np.arange(s) + 0.5) / s  # pole vertices take the centre of their column
    uv = np.stack([u, np.repeat(v[:, None], s + 1, axis=1)], axis=-1).reshape(-1, 2)
    idx = np.arange(n * (s + 1)).reshape(n, s + 1)
    tris = []
    for i in range(n - 1):
        a, b, c, d = idx[i, :-1], idx[i, 1:], idx[i + 1, :-1], idx[i + 1, 1:]
        if pole[i + 1]:  # fan into the pole vertex of this column
            tris.append(np.stack([a, c, b], 1))
        elif pole[i]:
            tris.append(np.stack([a, c, d], 1))
        else:
            tris += [np.stack([a, c, d], 1), np.stack([a, d, b], 1)]
    faces = np.concatenate(tris).astype(np.int64)
    verts, faces, uv = _compact(ring.reshape(-1, 3), faces, uv)
    return verts, _orient_outward(verts, faces), uv, ring


def _revolve(profile_rz, sections: int = SECTIONS):
    """Solid of revolution about +z from a profile of (r, z) points starting and ending on the axis."""
    p = np.array(profile_rz, dtype=np.float64)
    if abs(p[0, 0]) > 1e-9 or abs(p[-1, 0]) > 1e-9:
        raise ValueError("a revolved profile must start and end on the axis (r = 0)")
    p[[0, -1], 0] = 0.0
    m = len(p)
    centres = np.c_[np.zeros(m), np.zeros(m), p[:, 1]]
    return _sweep(centres, p[:, 0], np.tile([1.0, 0, 0], (m, 1)), np.tile([0, 1.0, 0], (m, 1)), sections)


def _frames(path: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Parallel-transport normal and binormal along a polyline (rotation-minimising frames)."""
    t = np.gradient(path, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    ref = np.array([0.0, 0.0, 1.0]) if abs(t[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    nrm = [np.cross(t[0], ref)]
    nrm[0] /= np.linalg.norm(nrm[0])
    for k in range(1, len(path)):
        q = nrm[-1] - np.dot(nrm[-1], t[k]) * t[k]
        nrm.append(q / np.linalg.norm(q))
    nrm = np.array(nrm)
    return nrm, np.cross(t, nrm)


def _chunks(n: int, size: int) -> list[range]:
    """Index ranges [i, i+size] (overlapping by one ring) covering 0..n-1."""
    return [range(i, min(i + size, n - 1) + 1) for i in range(0, n - 1, size)]


def _part_texture(name: str, part: str, pattern: str, colors: tuple, text: str | None = None) -> np.ndarray:
    return make_texture(pattern, colors, seed_from_name(f"{name}/{part}"), TEXTURE_SIZE, text)


def _revolved_part(obj: str, part: str, profile_rz, tex: tuple, cuts: list[int] | None = None,
                   sections: int = SECTIONS) -> _Part:
    """A solid of revolution; ``cuts`` are profile indices that split it into convex slabs for collision."""
    v, f, uv, ring = _revolve(profile_rz, sections)
    cuts = cuts or [0, len(profile_rz) - 1]
    coll = [ring[a: b + 1].reshape(-1, 3) for a, b in zip(cuts[:-1], cuts[1:])]
    return _Part(part, v, f, uv, _part_texture(obj, part, *tex), coll)


def _tube_part(obj: str, part: str, path, radius, tex: tuple, chunk: int = 3, sections: int = 16) -> _Part:
    """A capped tube along a 3-D polyline; ``radius`` scalar or per path point (m)."""
    path = np.asarray(path, dtype=np.float64)
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(path),))
    nrm, bin_ = _frames(path)
    rep = np.r_[0, np.arange(len(path)), len(path) - 1]  # duplicate the ends as poles (flat caps)
    radii = np.r_[0.0, r, 0.0]
    v, f, uv, ring = _sweep(path[rep], radii, nrm[rep], bin_[rep], sections)
    coll = [ring[list(rows)].reshape(-1, 3) for rows in _chunks(len(rep), chunk + 1)]
    return _Part(part, v, f, uv, _part_texture(obj, part, *tex), coll)


def _shell_part(obj: str, part: str, centreline_rz, thickness: float, tex: tuple, chunk: int = 2,
                sectors: int = 12) -> _Part:
    """A thin-walled solid of revolution (bowl, cup, shade): a wall of ``thickness`` (m) around a
    centreline of (r, z) points that starts on the axis. Collision pieces are annular sectors."""
    c = np.asarray(centreline_rz, dtype=np.float64)
    d = np.diff(c, axis=0)
    seg_n = np.c_[d[:, 1], -d[:, 0]] / np.linalg.norm(d, axis=1, keepdims=True)
    vn = np.vstack([seg_n[:1], seg_n[:-1] + seg_n[1:], seg_n[-1:]])
    vn /= np.linalg.norm(vn, axis=1, keepdims=True)
    cos_half = np.einsum("ij,ij->i", vn, np.vstack([seg_n[:1], seg_n]))  # mitre: keep the wall thickness
    off = vn * (thickness / 2.0 / np.maximum(cos_half, 0.3))[:, None]
    outer, inner = c + off, c - off
    outer[0, 0] = inner[0, 0] = 0.0
    profile = np.vstack([outer, inner[::-1]])
    v, f, uv, ring = _revolve(profile, SECTIONS)
    m = len(c)
    coll = []
    per = SECTIONS // sectors
    wall = [range(0, 2)] + [range(i, min(i + chunk, m - 1) + 1) for i in range(1, m - 1, chunk)]
    for rows in wall:
        idx = list(rows) + [len(profile) - 1 - k for k in rows]
        pts = ring[idx]  # rows × (S+1) × 3
        if rows[0] == 0:  # the first segment starts on the axis: a full disc
            coll.append(pts.reshape(-1, 3))
            continue
        for s in range(sectors):
            coll.append(pts[:, s * per: (s + 1) * per + 1].reshape(-1, 3))
    return _Part(part, v, f, uv, _part_texture(obj, part, *tex), coll)


def _box_part(obj: str, part: str, extents, tex: tuple, T: np.ndarray | None = None) -> _Part:
    """A box with box-projected UVs (each face maps the texture over its two in-plane axes)."""
    return _faceted_part(obj, part, trimesh.creation.box(extents=extents).vertices, tex, T)


def _faceted_part(obj: str, part: str, points, tex: tuple, T: np.ndarray | None = None) -> _Part:
    """The convex hull of ``points`` with box-projected UVs (vertices duplicated per face)."""
    hull = trimesh.convex.convex_hull(np.asarray(points, dtype=np.float64))
    tri = hull.vertices[hull.faces]  # F×3×3
    axis = np.abs(hull.face_normals).argmax(1)
    lo, hi = hull.bounds
    span = np.maximum(hi - lo, 1e-9)
    uvw = (tri - lo) / span
    keep = np.array([[1, 2], [0, 2], [0, 1]])[axis]  # the two in-plane axes of each face
    uv = np.take_along_axis(uvw, np.repeat(keep[:, None, :], 3, axis=1), axis=2)
    verts, inv = np.unique(np.c_[tri.reshape(-1, 3), uv.reshape(-1, 2)], axis=0, return_inverse=True)
    faces = inv.reshape(-1, 3).astype(np.int64)
    p = _Part(part, verts[:, :3], _orient_outward(verts[:, :3], faces), verts[:, 3:], _part_texture(obj, part, *tex),
              [hull.vertices])
    return p.transformed(T) if T is not None else p


def _rot(axis: str, deg: float) -> np.ndarray:
    unit = {"x": [1, 0, 0], "y": [0, 1, 0], "z": [0, 0, 1]}[axis]
    return trimesh.transformations.rotation_matrix(np.radians(deg), unit)


def _tr(x: float, y: float, z: float) -> np.ndarray:
    return trimesh.transformations.translation_matrix([x, y, z])


def _arc(centre, radius: float, a0: float, a1: float, n: int, plane: str = "xz") -> np.ndarray:
    """Points on a circular arc (angles in degrees) in the xz or xy plane."""
    a = np.radians(np.linspace(a0, a1, n))
    cx, cy, cz = centre
    if plane == "xz":
        return np.c_[cx + radius * np.cos(a), np.full(n, cy), cz + radius * np.sin(a)]
    return np.c_[cx + radius * np.cos(a), cy + radius * np.sin(a), np.full(n, cz)]


def _rounded_cylinder(r: float, h: float, bevel: float) -> list[tuple[float, float]]:
    """(r, z) profile of a cylinder with bevelled edges."""
    return [(0, 0), (r - bevel, 0), (r, bevel), (r, h - bevel), (r - bevel, h), (0, h)]


def _assemble(name: str, parts: list[_Part], nonconvex: bool, source: str = "builtin") -> ObjectModel:
    """Concatenate parts into one model: texture atlas bands, bottom-centre origin, convex pieces."""
    n = len(parts)
    tex = atlas([p.texture for p in parts])
    total_h = tex.shape[0]
    verts, faces, uvs, coll, off = [], [], [], [], 0
    for k, p in enumerate(parts):
        band_h = p.texture.shape[0] * tex.shape[1] / p.texture.shape[1]
        top = sum(q.texture.shape[0] * tex.shape[1] / q.texture.shape[1] for q in parts[:k])
        margin = 1.5  # texels, against bleeding from the neighbouring band
        v_hi = 1.0 - (top + margin) / total_h
        v_lo = 1.0 - (top + band_h - margin) / total_h
        uv = np.c_[np.clip(p.uv[:, 0], 0, 1), v_lo + np.clip(p.uv[:, 1], 0, 1) * (v_hi - v_lo)]
        verts.append(p.vertices)
        faces.append(p.faces + off)
        uvs.append(uv)
        coll.extend(p.collision)
        off += len(p.vertices)
    V = np.concatenate(verts)
    lo, hi = V.min(0), V.max(0)
    shift = -np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    hulls = []
    for pts in coll if nonconvex else []:  # snapped: see selfseg.generate.determinism
        h = trimesh.convex.convex_hull(snap(pts + shift))
        hulls.append((np.asarray(h.vertices, dtype=np.float64), np.asarray(h.faces, dtype=np.int64)))
    return ObjectModel(name=name, vertices=snap(V + shift), faces=np.concatenate(faces).astype(np.int64),
                       uv=snap(np.concatenate(uvs)), texture=tex, collision_parts=hulls if nonconvex else None,
                       nonconvex=nonconvex, source=source, part_names=[p.name for p in parts])


# ---- the builtin objects -------------------------------------------------------------------
def _boxes() -> list[ObjectModel]:
    specs = [("box_large", (0.20, 0.14, 0.08), ("label", ("orange", "white"), "CEREAL")),
             ("box_medium", (0.14, 0.10, 0.06), ("checks", ("blue", "white"))),
             ("box_small", (0.08, 0.06, 0.05), ("stripes", ("green", "yellow"))),
             ("book", (0.18, 0.13, 0.03), ("marble", ("dark_red", "beige"))),
             ("cube", (0.06, 0.06, 0.06), ("dots", ("purple", "white")))]
    return [_assemble(n, [_box_part(n, "body", e, t)], False) for n, e, t in specs]


def _round_convex() -> list[ObjectModel]:
    out = []
    cans = [("can_soda", 0.033, 0.12, ("label", ("white", "red"), "COLA")),
            ("can_soup", 0.040, 0.10, ("label", ("red", "white"), "SOUP")),
            ("chips_tube", 0.038, 0.22, ("label", ("brown", "yellow"), "CHIPS")),
            ("jar", 0.045, 0.11, ("gradient", ("teal", "cyan")))]
    for n, r, h, t in cans:
        out.append(_assemble(n, [_revolved_part(n, "body", _rounded_cylinder(r, h, 0.004), t)], False))
    a = np.radians(np.linspace(-90, 90, 25))
    out.append(_assemble("ball", [_revolved_part("ball", "body", np.c_[0.05 * np.cos(a), 0.05 + 0.05 * np.sin(a)],
                                                 ("plaid", ("navy", "white")))], False))
    out.append(_assemble("egg", [_revolved_part("egg", "body", np.c_[0.026 * np.cos(a), 0.0325 + 0.0325 * np.sin(a)],
                                                ("speckle", ("beige", "brown")))], False))
    cap = np.c_[0.02 * np.cos(a[:13]), 0.02 + 0.02 * np.sin(a[:13])]  # lower hemisphere of the capsule
    prof = np.vstack([cap, cap[::-1] * [1, -1] + [0, 0.14]])
    pill = _revolved_part("pill_tube", "body", prof, ("stripes", ("orange", "white")))
    out.append(_assemble("pill_tube", [pill], False))
    out.append(_assemble("flowerpot", [_revolved_part("flowerpot", "body", [(0, 0), (0.04, 0), (0.06, 0.09), (0, 0.09)],
                                                      ("noise", ("terracotta", "brown")))], False))
    out.append(_assemble("hex_box", [_revolved_part("hex_box", "body", [(0, 0), (0.05, 0), (0.05, 0.05), (0, 0.05)],
                                                    ("diag_stripes", ("magenta", "pink")), sections=6)], False))
    wedge = [(0, 0, 0), (0.10, 0, 0), (0, 0.08, 0), (0, 0, 0.05), (0.10, 0, 0.05), (0, 0.08, 0.05)]
    out.append(_assemble("cheese_wedge", [_faceted_part("cheese_wedge", "body", wedge, ("dots", ("orange", "beige")))],
                         False))
    return out


def _lamp() -> ObjectModel:
    base = _revolved_part("lamp", "base", _rounded_cylinder(0.06, 0.02, 0.005), ("solid", ("black", "grey")))
    path = np.vstack([np.c_[np.zeros(6), np.zeros(6), np.linspace(0.015, 0.13, 6)],
                      _arc((0.06, 0, 0.13), 0.06, 175, 30, 10)])
    neck = _tube_part("lamp", "gooseneck", path, 0.007, ("stripes", ("silver", "grey")))
    shade = _shell_part("lamp", "shade", [(0, 0.07), (0.015, 0.07), (0.055, 0.0)], 0.004,
                        ("noise", ("red", "dark_red")))
    end, tangent = path[-1], path[-1] - path[-2]
    tilt = np.degrees(np.arctan2(tangent[0], tangent[2]))  # point the shade's axis along the neck's end
    shade = shade.transformed(_tr(*end) @ _rot("y", tilt + 180) @ _tr(0, 0, -0.068))
    return _assemble("lamp", [base, neck, shade], True)


def _dumbbell() -> ObjectModel:
    w = _rounded_cylinder(0.035, 0.03, 0.005)
    left = _revolved_part("dumbbell", "weight_left", w, ("checks", ("black", "grey")))
    right = _revolved_part("dumbbell", "weight_right", w, ("checks", ("black", "grey")))
    bar = _tube_part("dumbbell", "bar", [(-0.1, 0, 0), (0.1, 0, 0)], 0.012, ("stripes", ("silver", "black")))
    lay = _rot("y", 90)
    return _assemble("dumbbell", [left.transformed(_tr(-0.085, 0, 0) @ lay), bar,
                                  right.transformed(_tr(0.055, 0, 0) @ lay)], True)


def _mug_like(name: str, radius: float, height: float, handle_r: float, tex_body: tuple, tex_handle: tuple,
              top_radius: float | None = None) -> ObjectModel:
    t = 0.005
    body = _shell_part(name, "body", [(0, t / 2), (radius - t / 2, t / 2), (top_radius or radius, height)], t, tex_body)
    rim_r = ((top_radius or radius) + radius) / 2
    # The handle's ends (±100°) reach inside the wall, so body and handle are one rigid piece.
    handle = _tube_part(name, "handle", _arc((rim_r, 0, height * 0.55), handle_r, -100, 100, 14), 0.006, tex_handle)
    return _assemble(name, [body, handle], True)


def _bowl() -> ObjectModel:
    a = np.radians(np.linspace(-90, 0, 7))
    wall = np.c_[0.045 + 0.035 * np.cos(a), 0.0625 + 0.06 * np.sin(a)]
    centre = np.vstack([[0, 0.0025], wall])
    return _assemble("bowl", [_shell_part("bowl", "body", centre, 0.005, ("dots", ("blue", "white")))], True)


def _bottle() -> ObjectModel:
    body = [(0, 0), (0.033, 0), (0.037, 0.005), (0.037, 0.14), (0.030, 0.165), (0.018, 0.185), (0.014, 0.195),
            (0.014, 0.215), (0, 0.215)]
    cap = _rounded_cylinder(0.016, 0.025, 0.002)
    # convex slabs for collision: body, shoulder, neck
    body_part = _revolved_part("bottle", "body", body, ("label", ("green", "white"), "WATER"), [0, 3, 5, 8])
    cap_part = _revolved_part("bottle", "cap", [(r, z + 0.21) for r, z in cap], ("solid", ("blue", "blue")))
    return _assemble("bottle", [body_part, cap_part], True)


def _hammer() -> ObjectModel:
    handle = _tube_part("hammer", "handle", [(0, 0, 0), (0.21, 0, 0)], 0.012, ("wood", ("tan", "brown")))
    head = _box_part("hammer", "head", (0.03, 0.11, 0.03), ("noise", ("grey", "silver")), _tr(0.22, 0.015, 0))
    return _assemble("hammer", [handle, head], True)


def _drill() -> ObjectModel:
    body = _box_part("drill", "body", (0.16, 0.05, 0.06), ("stripes", ("yellow", "black")), _tr(0.0, 0, 0.17))
    handle = _tube_part("drill", "handle", [(-0.03, 0, 0.145), (-0.045, 0, 0.035)], 0.018, ("solid", ("black", "grey")))
    chuck = _tube_part("drill", "chuck", [(0.075, 0, 0.17), (0.12, 0, 0.17)], 0.012, ("checks", ("silver", "black")))
    battery = _box_part("drill", "battery", (0.08, 0.06, 0.03), ("label", ("black", "yellow"), "18V"),
                        _tr(-0.04, 0, 0.015))
    return _assemble("drill", [body, handle, chuck, battery], True)


def _banana() -> ObjectModel:
    path = _arc((0, 0, 0.13), 0.12, 215, 325, 14)
    s = np.linspace(0.0, 1.0, len(path))
    radius = 0.004 + 0.014 * np.sin(np.pi * s) ** 0.6
    body = _tube_part("banana", "body", path, radius, ("speckle", ("yellow", "brown")), chunk=3)
    return _assemble("banana", [body], True)


def _duck() -> ObjectModel:
    import pybullet_data
    from PIL import Image

    folder = Path(pybullet_data.getDataPath())
    mesh = trimesh.load(folder / "duck.obj", force="mesh", process=False)
    pieces = trimesh.load(folder / "duck_vhacd.obj", force="mesh", process=False).split(only_watertight=False)
    y_up_to_z_up = _rot("x", 90)
    scale = 0.10 / float(np.max(mesh.extents))  # longest side 10 cm
    T = np.diag([scale, scale, scale, 1.0]) @ y_up_to_z_up
    texture = np.asarray(Image.open(folder / "duckCM.png").convert("RGB"))
    uv = np.asarray(mesh.visual.uv, dtype=np.float64)
    part = _Part("body", trimesh.transform_points(mesh.vertices, T), np.asarray(mesh.faces, dtype=np.int64),
                 uv, texture, [trimesh.transform_points(p.vertices, T) for p in pieces])
    return _assemble("duck", [part], True, source="pybullet_data:duck.obj")


def builtin_library() -> list[ObjectModel]:
    """The 25 builtin objects (10 non-convex), in a fixed order with fixed names and textures."""
    return (_boxes() + _round_convex()
            + [_lamp(), _dumbbell(),
               _mug_like("mug", 0.04, 0.095, 0.028, ("stripes", ("white", "red")), ("solid", ("red", "red"))),
               _bowl(), _bottle(),
               _mug_like("pitcher", 0.055, 0.17, 0.045, ("marble", ("teal", "white")), ("solid", ("teal", "teal")),
                         top_radius=0.05),
               _duck(), _hammer(), _banana(), _drill()])


# 17 objects for the paper-synthetic preset (HomebrewedDB has 17 toys): every non-convex object
# and seven convex ones of different shapes.
PAPER_SUBSET: tuple[str, ...] = ("lamp", "dumbbell", "mug", "bowl", "bottle", "pitcher", "duck", "hammer", "banana",
                                 "drill", "box_medium", "box_small", "can_soda", "ball", "jar", "flowerpot",
                                 "cheese_wedge")


# ---- the `paper` library: chunky multi-part toys ------------------------------------------
# In the spirit of the paper's HomebrewedDB toys: 6–20 cm, every part a convex primitive at
# least ~2 cm thick, parts meeting at concave creases (where LCCP splits an object into parts that
# graph matching can join again), one distinct texture per part.
def _sphere_part(obj: str, part: str, r: float, centre, tex: tuple) -> _Part:
    a = np.radians(np.linspace(-90, 90, 25))
    prof = np.c_[r * np.cos(a), r + r * np.sin(a)]
    return _revolved_part(obj, part, prof, tex).transformed(_tr(centre[0], centre[1], centre[2] - r))


def _cylinder_part(obj: str, part: str, r: float, length: float, tex: tuple, T: np.ndarray) -> _Part:
    """A bevelled cylinder along +z from z = 0 to ``length``, then placed by ``T``."""
    return _revolved_part(obj, part, _rounded_cylinder(r, length, min(0.003, r / 3)), tex).transformed(T)


def _prism(points_xz, y0: float, y1: float) -> np.ndarray:
    """Corners of a prism: a convex polygon in the xz plane extruded from y0 to y1 (m)."""
    p = np.asarray(points_xz, dtype=np.float64)
    return np.vstack([np.c_[p[:, 0], np.full(len(p), y), p[:, 1]] for y in (y0, y1)])


def _toy_car() -> ObjectModel:
    n = "toy_car"
    parts = [_box_part(n, "body", (0.14, 0.065, 0.035), ("solid", ("red", "dark_red")), _tr(0, 0, 0.0375)),
             _box_part(n, "cabin", (0.07, 0.055, 0.03), ("checks", ("white", "blue")), _tr(-0.01, 0, 0.07))]
    for k, (x, y) in enumerate([(0.045, 0.035), (0.045, -0.035), (-0.045, 0.035), (-0.045, -0.035)]):
        parts.append(_cylinder_part(n, f"wheel{k}", 0.02, 0.02, ("dots", ("black", "grey")),
                                    _tr(x, y + (0.01 if y > 0 else -0.01), 0.02) @ _rot("x", 90)))
    return _assemble(n, parts, True)


def _toy_rocket() -> ObjectModel:
    n = "toy_rocket"
    body = _revolved_part(n, "body", [(0, 0), (0.025, 0), (0.025, 0.10), (0.012, 0.135), (0, 0.145)],
                          ("stripes", ("white", "red")))
    fin = _prism([(0.02, 0.0), (0.055, 0.0), (0.02, 0.05)], -0.01, 0.01)
    fins = [_faceted_part(n, f"fin{k}", fin, ("solid", ("blue", "navy")), _rot("z", 120 * k)) for k in range(3)]
    return _assemble(n, [body, *fins], True)


def _snowman() -> ObjectModel:
    n = "snowman"
    return _assemble(n, [_sphere_part(n, "bottom", 0.045, (0, 0, 0.045), ("speckle", ("white", "grey"))),
                         _sphere_part(n, "middle", 0.035, (0, 0, 0.115), ("dots", ("white", "black"))),
                         _sphere_part(n, "head", 0.025, (0, 0, 0.17), ("noise", ("white", "orange")))], True)


def _toy_robot() -> ObjectModel:
    n = "toy_robot"
    parts = [_box_part(n, "torso", (0.06, 0.04, 0.07), ("label", ("silver", "blue"), "BOT"), _tr(0, 0, 0.075)),
             _box_part(n, "head", (0.04, 0.035, 0.035), ("plaid", ("yellow", "black")), _tr(0, 0, 0.1275))]
    parts += [_box_part(n, f"leg{k}", (0.025, 0.03, 0.04), ("solid", ("navy", "blue")), _tr(x, 0, 0.02))
              for k, x in enumerate((0.0175, -0.0175))]
    parts += [_box_part(n, f"arm{k}", (0.02, 0.025, 0.06), ("stripes", ("orange", "grey")), _tr(x, 0, 0.08))
              for k, x in enumerate((0.04, -0.04))]
    return _assemble(n, parts, True)


def _mushroom() -> ObjectModel:
    n = "mushroom"
    stem = _revolved_part(n, "stem", [(0, 0), (0.022, 0), (0.02, 0.05), (0, 0.05)], ("wood", ("beige", "tan")))
    cap = _revolved_part(n, "cap", [(0, 0.045), (0.048, 0.045), (0.052, 0.055), (0.047, 0.07), (0.032, 0.085),
                                    (0, 0.092)], ("dots", ("red", "white")))
    return _assemble(n, [stem, cap], True)


def _toy_house() -> ObjectModel:
    n = "toy_house"
    body = _box_part(n, "walls", (0.08, 0.07, 0.06), ("checks", ("beige", "brown")), _tr(0, 0, 0.03))
    roof = _faceted_part(n, "roof", _prism([(-0.05, 0.055), (0.05, 0.055), (0.05, 0.065), (0.0, 0.10), (-0.05, 0.065)],
                                           -0.05, 0.05), ("diag_stripes", ("dark_red", "terracotta")), _rot("z", 90))
    chimney = _box_part(n, "chimney", (0.02, 0.02, 0.035), ("solid", ("grey", "black")), _tr(0.02, 0.02, 0.095))
    return _assemble(n, [body, roof, chimney], True)


def _block_l() -> ObjectModel:
    n = "block_l"
    return _assemble(n, [_box_part(n, "long", (0.12, 0.04, 0.04), ("solid", ("lime", "green")), _tr(0, 0, 0.02)),
                         _box_part(n, "foot", (0.04, 0.04, 0.04), ("diag_stripes", ("purple", "magenta")),
                                   _tr(-0.04, 0.04, 0.02))], True)


def _toy_dumbbell() -> ObjectModel:
    n = "toy_dumbbell"
    return _assemble(n, [_sphere_part(n, "ball0", 0.035, (0.065, 0, 0.035), ("marble", ("teal", "cyan"))),
                         _cylinder_part(n, "bar", 0.012, 0.12, ("solid", ("gold", "yellow")),
                                        _tr(-0.06, 0, 0.035) @ _rot("y", 90)),
                         _sphere_part(n, "ball1", 0.035, (-0.065, 0, 0.035), ("marble", ("pink", "magenta")))], True)


def _toy_tank() -> ObjectModel:
    n = "toy_tank"
    return _assemble(n, [_box_part(n, "hull", (0.14, 0.08, 0.04), ("noise", ("dark_green", "green")), _tr(0, 0, 0.02)),
                         _cylinder_part(n, "turret", 0.035, 0.025, ("speckle", ("tan", "brown")), _tr(-0.01, 0, 0.04)),
                         _cylinder_part(n, "barrel", 0.01, 0.075, ("stripes", ("black", "grey")),
                                        _tr(0.015, 0, 0.0525) @ _rot("y", 90))], True)


def _toy_plane() -> ObjectModel:
    n = "toy_plane"
    a = np.radians(np.linspace(-90, 90, 13))
    cap = np.c_[0.02 * np.cos(a[:7]), 0.02 + 0.02 * np.sin(a[:7])]
    fuselage = _revolved_part(n, "fuselage", np.vstack([cap, cap[::-1] * [1, -1] + [0, 0.16]]),
                              ("label", ("white", "navy"), "AIR")).transformed(_tr(-0.08, 0, 0.02) @ _rot("y", 90))
    wings = _box_part(n, "wings", (0.04, 0.16, 0.02), ("solid", ("orange", "yellow")), _tr(0.01, 0, 0.02))
    tail = _box_part(n, "tail", (0.03, 0.02, 0.04), ("checks", ("red", "white")), _tr(-0.06, 0, 0.045))
    return _assemble(n, [fuselage, wings, tail], True)


def _pawn() -> ObjectModel:
    n = "pawn"
    body = _revolved_part(n, "body", [(0, 0), (0.035, 0), (0.035, 0.015), (0.026, 0.022), (0.016, 0.065), (0.025, 0.07),
                                      (0.025, 0.076), (0, 0.078)], ("gradient", ("purple", "pink")))
    head = _sphere_part(n, "head", 0.022, (0, 0, 0.095), ("solid", ("pink", "purple")))
    return _assemble(n, [body, head], True)


def _toy_hammer() -> ObjectModel:
    n = "toy_hammer"
    return _assemble(n, [_cylinder_part(n, "handle", 0.012, 0.13, ("wood", ("tan", "brown")),
                                        _tr(-0.07, 0, 0.0175) @ _rot("y", 90)),
                         _box_part(n, "head", (0.035, 0.09, 0.035), ("plaid", ("blue", "cyan")), _tr(0.075, 0, 0.0175))],
                     True)


def paper_library() -> list[ObjectModel]:
    """The `paper` library: 12 chunky multi-part toys and the pybullet_data duck, in a fixed order."""
    return [_toy_car(), _toy_rocket(), _snowman(), _toy_robot(), _mushroom(), _toy_house(), _block_l(),
            _toy_dumbbell(), _toy_tank(), _toy_plane(), _pawn(), _toy_hammer(), _duck()]


# ---- user meshes ---------------------------------------------------------------------------
def _pick_mesh(folder: Path) -> Path:
    """The one mesh to use from an object subfolder (YCB layout: google_16k/textured.obj)."""
    found = sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in MESH_EXTENSIONS)
    if not found:
        raise ObjectLibraryError(f"{folder}: object folder contains no mesh ({', '.join(MESH_EXTENSIONS)})")
    rank = {e: i for i, e in enumerate(MESH_EXTENSIONS)}
    return min(found, key=lambda p: (p.stem.lower() != "textured", rank[p.suffix.lower()], len(p.parts), str(p)))


def _texture_of(mesh: trimesh.Trimesh, name: str) -> tuple[np.ndarray, np.ndarray]:
    """UV (V×2 in [0,1]) and texture image of a loaded mesh: its own texture if it has one,
    else its vertex/face colours baked into a texel-per-vertex image, else a procedural texture."""
    vis = mesh.visual
    if isinstance(vis, trimesh.visual.TextureVisuals) and vis.uv is not None and len(vis.uv) == len(mesh.vertices):
        mat = vis.material
        img = getattr(mat, "image", None)
        if img is None:
            img = getattr(mat, "baseColorTexture", None)
        if img is not None:
            uv = np.asarray(vis.uv, dtype=np.float64)
            uv = np.where((uv < 0) | (uv > 1), uv - np.floor(uv), uv)  # tiled coordinates wrap
            return uv, np.asarray(img.convert("RGB"))
        vis = vis.to_color()
    colors = None
    if isinstance(vis, trimesh.visual.ColorVisuals) and vis.kind in ("vertex", "face"):
        colors = np.asarray(vis.vertex_colors)[:, :3]
    n = len(mesh.vertices)
    if colors is None:  # untextured, uncoloured: a procedural texture with box-projected UVs
        lo, hi = mesh.bounds
        uv = (mesh.vertices[:, :2] - lo[:2]) / np.maximum(hi[:2] - lo[:2], 1e-9)
        return uv, make_texture("noise", ("grey", "white"), seed_from_name(name), TEXTURE_SIZE)
    side = int(np.ceil(np.sqrt(n)))
    tex = np.zeros((side * side, 3), dtype=np.uint8)
    tex[:n] = colors
    k = np.arange(n)
    uv = np.c_[((k % side) + 0.5) / side, 1.0 - ((k // side) + 0.5) / side]
    return uv, tex.reshape(side, side, 3)


def check_mesh_limits(path: Path, vertices_m: np.ndarray, n_faces: int) -> None:
    """Refuse, with one line naming the file, a mesh the generator cannot use: too many faces, non-finite,
    larger than :data:`MAX_EXTENT_M` (centimetre or millimetre units named as such), smaller than
    :data:`MIN_EXTENT_M`, or flat (thinner than :data:`MIN_THICKNESS_M` along its thinnest principal axis)."""
    if n_faces > MAX_FACES:
        raise ObjectLibraryError(f"{path}: {n_faces} faces, more than the limit of {MAX_FACES}; decimate it first "
                                 f"(e.g. Blender's Decimate modifier with ratio {MAX_FACES / n_faces:.3f})")
    if not np.isfinite(vertices_m).all():
        raise ObjectLibraryError(f"{path}: mesh has non-finite vertices")
    ext = float(np.max(vertices_m.max(0) - vertices_m.min(0)))
    if ext > MAX_EXTENT_M:
        unit = " (is it in millimetres? scale it by 0.001)" if ext > 50 else \
            " (is it in centimetres? scale it by 0.01)" if ext > 5 else ""
        raise ObjectLibraryError(f"{path}: mesh is {ext:.3g} units across; meshes must be in metres and at most "
                                 f"{MAX_EXTENT_M} m across to fit the camera's view{unit}")
    if ext < MIN_EXTENT_M:
        raise ObjectLibraryError(f"{path}: mesh is {ext * 1000:.3g} mm across, under {MIN_EXTENT_M * 1000:.0f} mm: "
                                 "too small to be seen by the camera (meshes must be in metres)")
    centred = vertices_m - vertices_m.mean(0)
    axis = np.linalg.eigh(centred.T @ centred)[1][:, 0]  # thinnest principal direction
    thickness = float(np.ptp(centred @ axis))
    if thickness < MIN_THICKNESS_M:
        raise ObjectLibraryError(f"{path}: mesh is flat ({thickness * 1000:.3g} mm thick; its convex hull has no "
                                 "volume); objects need a closed, solid shape")


def load_user_object(path: str | os.PathLike, name: str | None = None) -> ObjectModel:
    """One user mesh file (OBJ with MTL and texture, PLY or GLB; metres) as an :class:`ObjectModel`.

    The model frame keeps the file's coordinates. Non-convex meshes (volume below 90 % of the
    convex hull's, or not watertight) get ``collision_parts=None`` and are decomposed by VHACD
    in the physics step.
    """
    path = Path(path)
    name = name or path.stem
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for corrupt files
        raise ObjectLibraryError(f"{path}: unreadable mesh ({type(e).__name__}: {e})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ObjectLibraryError(f"{path}: unreadable mesh (no triangles found)")
    check_mesh_limits(path, np.asarray(mesh.vertices, dtype=np.float64), len(mesh.faces))
    uv, tex = _texture_of(mesh, name)
    merged = trimesh.Trimesh(mesh.vertices, mesh.faces)  # processed copy: seams merged
    convex = merged.is_watertight and merged.volume > 0.9 * merged.convex_hull.volume
    return ObjectModel(name=name, vertices=snap(mesh.vertices),
                       faces=np.asarray(mesh.faces, dtype=np.int64), uv=np.clip(uv, 0.0, 1.0),
                       texture=np.ascontiguousarray(tex, dtype=np.uint8), collision_parts=None, nonconvex=not convex,
                       source=f"user:{path.resolve()}")


def load_user_objects(folder: str | os.PathLike) -> list[ObjectModel]:
    """All objects of a user folder, sorted by name: each mesh file directly in ``folder`` is one
    object (named by its stem), and each subfolder is one object (named by the subfolder; its mesh
    is found recursively, preferring ``textured.*``, then OBJ over PLY/GLB)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ObjectLibraryError(f"{folder}: objects folder does not exist")
    items: list[tuple[str, Path]] = []
    for entry in sorted(folder.iterdir()):
        if entry.name.startswith("."):
            continue
        if entry.is_dir():
            items.append((entry.name, _pick_mesh(entry)))
        elif entry.suffix.lower() in MESH_EXTENSIONS:
            items.append((entry.stem, entry))
    if not items:
        raise ObjectLibraryError(f"{folder}: no meshes found ({', '.join(MESH_EXTENSIONS)} files or subfolders)")
    names = [n for n, _ in items]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ObjectLibraryError(f"{folder}: several objects share the name(s) {dup}")
    return [load_user_object(p, n) for n, p in items]


# ---- writing models into a dataset ---------------------------------------------------------
def _diameter(points: np.ndarray, chunk: int = 1024) -> float:
    """Largest distance between two points: the convex hull first (O(n log n)), then its vertices compared
    in chunks (memory O(chunk × hull vertices))."""
    hull = trimesh.convex.convex_hull(points).vertices if len(points) > 4 else np.asarray(points, dtype=np.float64)
    best = 0.0
    for i in range(0, len(hull), chunk):
        d2 = ((hull[i:i + chunk, None, :] - hull[None, :, :]) ** 2).sum(-1)
        best = max(best, float(d2.max()))
    return float(np.sqrt(best))


def _ply_bytes(vertices_mm: np.ndarray, faces: np.ndarray, colors: np.ndarray) -> bytes:
    """Binary little-endian PLY with float vertices, uchar colours and int face indices."""
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(vertices_mm)}\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n").encode("ascii")
    vdt = np.dtype([("p", "<f4", 3), ("c", "u1", 3)])
    v = np.empty(len(vertices_mm), vdt)
    v["p"], v["c"] = vertices_mm, colors
    fdt = np.dtype([("n", "u1"), ("i", "<i4", 3)])
    f = np.empty(len(faces), fdt)
    f["n"], f["i"] = 3, faces
    return header + v.tobytes() + f.tobytes()


def models_info_entry(obj: ObjectModel) -> dict:
    """BOP models_info fields (mm) for one object, plus its name and source."""
    mm = obj.vertices * 1000.0
    lo, hi = mm.min(0), mm.max(0)
    return {"diameter": _diameter(mm), "min_x": float(lo[0]), "min_y": float(lo[1]), "min_z": float(lo[2]),
            "size_x": float(hi[0] - lo[0]), "size_y": float(hi[1] - lo[1]), "size_z": float(hi[2] - lo[2]),
            "name": obj.name, "source": obj.source}


def write_models(dataset_root: str | os.PathLike, objects: list[ObjectModel]) -> None:
    """Write ``models/obj_{i:06d}.ply`` (mm, vertex colours from the texture; obj_id = index + 1)
    and ``models/models_info.json`` into a dataset folder (atomic writes)."""
    root = Path(dataset_root)
    info = {}
    for i, obj in enumerate(objects):
        obj_id = i + 1
        atomic_write_bytes(root / MODEL_PLY.format(obj_id=obj_id),
                           _ply_bytes(obj.vertices * 1000.0, obj.faces, obj.vertex_colors()))
        info[str(obj_id)] = models_info_entry(obj)
    write_json(root / MODELS_INFO, info)
