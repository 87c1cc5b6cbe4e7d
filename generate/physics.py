"""Physics drop with pybullet: objects fall onto a finite table and come to rest.

World frame: z up, the table top is the square |x|, |y| <= ``table_half_extent_m`` at z = 0.
Every object is a rigid body whose collision shape is a compound of convex pieces: its
``collision_parts`` (decomposition by parts), a VHACD decomposition for non-convex objects
without parts (cached on disk, keyed by the mesh's hash), or its convex hull. The body frame
sits at the pieces' volume-weighted centroid with the model's axes; returned poses are
``T_world_obj`` of the *model* frame in metres.
"""
from __future__ import annotations

import contextlib
import hashlib
import math
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np
import pybullet as pb
import trimesh

from selfseg.fileio import atomic_write_bytes, atomic_write_text
from selfseg.generate.determinism import is_pinned, snap, snap_pose
from selfseg.generate.objects import ObjectModel

TABLE_ID = -1  # stands for the table in DropResult.penetrations and DropResult.contacts


@dataclass
class PhysicsConfig:
    """Drop and settling parameters (SI units: m, s, kg)."""

    table_half_extent_m: float = 0.35  # the table top is a square of side 2× this, centred at the origin
    drop_radius_m: float = 0.15  # objects start above a disc of this radius around the table centre
    # "pile": each object starts at a random point of the disc, above whatever is there (clutter, contact);
    # "spread": it starts where its bounding circle keeps spread_gap_m from every body already dropped (in
    # x, y; the best of spread_tries random points when none does), just above the table (contact is rare)
    layout: str = "pile"
    spread_gap_m: float = 0.01
    spread_tries: int = 200
    drop_height_m: float = 0.03  # clearance of an object's bounding sphere above the table ...
    drop_gap_m: float = 0.01  # ... and above the bounding boxes of the objects below it
    drop_interval_steps: int = 60  # objects are dropped one after another, this many steps apart
    time_step_s: float = 1.0 / 240.0
    max_steps: int = 2400  # per settling phase (10 s of simulated time at 240 Hz)
    settle_linear_mps: float = 0.005  # an object is at rest below this speed ...
    settle_angular_radps: float = 0.05  # ... and this angular speed ...
    settle_steps: int = 48  # ... for this many consecutive steps
    settle_phases: int = 3  # after removing unsettled objects the rest settles again, at most this often
    lateral_friction: float = 0.7
    rolling_friction: float = 0.002  # m; lets balls and cans come to rest
    spinning_friction: float = 0.002
    linear_damping: float = 0.04
    angular_damping: float = 0.1
    density_kg_m3: float = 400.0
    solver_iterations: int = 50
    max_attempts: int = 10  # re-drops (new sub-seed) while fewer than min_kept objects remain
    penetration_report_m: float = 0.002  # pairs deeper than this are listed in DropResult.penetrations
    contact_distance_m: float = 0.002  # pairs closer than this are listed in DropResult.contacts
    vhacd_resolution: int = 100000  # voxels for VHACD (5–13 s per mesh at 100000)

    def __post_init__(self) -> None:
        if self.layout not in ("pile", "spread"):
            raise ValueError(f"physics.layout must be 'pile' or 'spread', got {self.layout!r}")
        if self.spread_tries < 1:
            raise ValueError(f"physics.spread_tries must be at least 1, got {self.spread_tries}")


@dataclass
class DropResult:
    poses: dict[int, np.ndarray]  # index into `objects` -> T_world_obj 4×4 (m), objects at rest on the table
    removed: list[int]  # indices that fell off the table or never settled (sorted)
    attempts: int  # drops performed (1 = the first drop was kept)
    steps: int = 0  # simulation steps of the kept drop
    max_penetration_m: float = 0.0  # deepest penetration between kept bodies or with the table (collision shapes)
    penetrations: dict[tuple[int, int], float] = field(default_factory=dict)  # (i, j or TABLE_ID) -> depth (m)
    contacts: list[tuple[int, int]] = field(default_factory=list)  # touching pairs (i, j or TABLE_ID), i < j


# ---- collision geometry --------------------------------------------------------------------
def mesh_hash(obj: ObjectModel) -> str:
    """Hash of an object's geometry (vertices and faces), the key of its cached decomposition."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(obj.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(obj.faces, dtype=np.int64).tobytes())
    return h.hexdigest()[:16]


def _obj_text(pieces: list[tuple[np.ndarray, np.ndarray]]) -> str:
    """Wavefront OBJ with one ``o`` group per piece."""
    lines, base = [], 1
    for k, (v, f) in enumerate(pieces):
        lines.append(f"o piece{k}")
        lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in v]
        lines += [f"f {a + base} {b + base} {c + base}" for a, b, c in f]
        base += len(v)
    return "\n".join(lines) + "\n"


def read_obj_pieces(path: Path) -> list[np.ndarray]:
    """Vertex sets of the ``o``/``g`` groups of an OBJ file (e.g. VHACD output)."""
    verts, groups, cur = [], [], []
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            tok = line.split()
            if not tok:
                continue
            if tok[0] == "v":
                verts.append([float(t) for t in tok[1:4]])
            elif tok[0] in ("o", "g"):
                if cur:
                    groups.append(cur)
                cur = []
            elif tok[0] == "f":
                cur += [int(t.split("/")[0]) for t in tok[1:]]
    if cur:
        groups.append(cur)
    v = np.asarray(verts, dtype=np.float64)
    pieces = [v[np.unique(np.abs(np.asarray(g)) - 1)] for g in groups]
    if not pieces:
        raise ValueError(f"{path}: no faces found")
    return pieces


@contextlib.contextmanager
def _stdout_to_devnull() -> Iterator[None]:
    """Silence C-level writes to file descriptor 1 (pybullet's VHACD output)."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def vhacd_pieces(obj: ObjectModel, cache_dir: Path | None, resolution: int = 100000) -> list[np.ndarray]:
    """Convex decomposition (VHACD) of a mesh as vertex sets in the model frame.

    With ``cache_dir`` the result is stored as ``vhacd_<meshhash>_<resolution>.obj`` and reused; a process whose
    libraries are not pinned (:mod:`selfseg.generate.determinism`) keeps its own ``..._unpinned.obj``, so that
    it never hands its machine-dependent result to the ``generate_scenes`` command.
    """
    key = f"vhacd_{mesh_hash(obj)}_{resolution}{'' if is_pinned(os.environ) else '_unpinned'}.obj"
    if cache_dir is not None and (Path(cache_dir) / key).exists():
        return read_obj_pieces(Path(cache_dir) / key)
    with tempfile.TemporaryDirectory(prefix="selfseg_vhacd_") as tmp:
        src, dst = Path(tmp) / "in.obj", Path(tmp) / "out.obj"
        atomic_write_text(src, _obj_text([(obj.vertices, obj.faces)]))
        with _stdout_to_devnull():  # VHACD prints its whole parameter list and progress
            pb.vhacd(str(src), str(dst), str(Path(tmp) / "log.txt"), resolution=resolution)
        if not dst.exists():
            raise RuntimeError(f"VHACD produced no decomposition for object {obj.name!r} ({obj.source})")
        if cache_dir is not None:
            atomic_write_bytes(Path(cache_dir) / key, dst.read_bytes())
        return read_obj_pieces(dst)


@dataclass
class CollisionBody:
    """Collision geometry of one object in its body frame (model frame shifted by -com)."""

    pieces: list[tuple[np.ndarray, np.ndarray]]  # convex hulls (vertices, faces), body frame
    com: np.ndarray  # body origin in the model frame (m)
    mass: float  # kg
    radius: float  # bounding-sphere radius about the body origin (m)


def collision_body(obj: ObjectModel, cfg: PhysicsConfig, cache_dir: Path | None) -> CollisionBody:
    """Convex pieces, centre of mass and mass of an object."""
    if obj.collision_parts is not None:
        point_sets = [v for v, _ in obj.collision_parts]
    elif obj.nonconvex:
        point_sets = vhacd_pieces(obj, cache_dir, cfg.vhacd_resolution)
    else:
        point_sets = [obj.vertices]
    hulls = [trimesh.convex.convex_hull(snap(p)) for p in point_sets]
    vols = snap([max(h.volume, 1e-9) for h in hulls], 40)
    com = snap((np.array([h.center_mass for h in hulls]) * vols[:, None]).sum(0) / vols.sum())
    pieces = [(np.asarray(h.vertices) - com, np.asarray(h.faces)) for h in hulls]  # exact: both on the grid
    radius = float(snap(np.sqrt(((obj.vertices - com) ** 2).sum(1)).max()))
    return CollisionBody(pieces, com, max(float(snap(vols.sum() * cfg.density_kg_m3)), 0.01), radius)


# ---- simulation ----------------------------------------------------------------------------
def _random_rotation(rng: np.random.Generator) -> list[float]:
    """Uniform random quaternion (x, y, z, w)."""
    q = rng.normal(size=4).tolist()
    n = math.hypot(*q)  # no BLAS: see selfseg.generate.determinism
    return [x / n for x in q]


def _disc_point(rng: np.random.Generator, radius_m: float) -> np.ndarray:
    """A uniform random point (x, y) of the disc of ``radius_m`` around the table centre."""
    a, r = float(rng.uniform(0, 2 * np.pi)), radius_m * math.sqrt(rng.uniform())
    return np.array([r * math.cos(a), r * math.sin(a)])


def _xy_gaps(xy: np.ndarray, boxes: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Distance (m) in x, y from ``xy`` to each axis-aligned box (lo, hi); 0 inside."""
    return np.array([math.hypot(*np.maximum(0.0, np.maximum(lo[:2] - xy, xy - hi[:2]))) for lo, hi in boxes])


def _start_position(cid: int, radius: float, ids: dict[int, int], rng: np.random.Generator,
                    cfg: PhysicsConfig) -> list[float]:
    """A centre above the drop disc whose bounding sphere clears the table and every body's AABB
    (see :attr:`PhysicsConfig.layout`)."""
    boxes = [tuple(np.asarray(c) for c in pb.getAABB(body, physicsClientId=cid)) for body in ids.values()]
    xy = _disc_point(rng, cfg.drop_radius_m)
    if cfg.layout == "spread" and boxes:
        best = -np.inf
        for _ in range(cfg.spread_tries):
            clearance = float(_xy_gaps(xy, boxes).min()) - radius
            if clearance > best:
                best, chosen = clearance, xy
            if clearance >= cfg.spread_gap_m:
                break
            xy = _disc_point(rng, cfg.drop_radius_m)
        xy = chosen
    z = cfg.drop_height_m + radius
    for (lo, hi), gap in zip(boxes, _xy_gaps(xy, boxes)):
        if gap < radius + cfg.drop_gap_m:
            z = max(z, hi[2] + radius + cfg.drop_gap_m)
    return [float(xy[0]), float(xy[1]), float(z)]


def _pose(cid: int, body: int, com: np.ndarray) -> np.ndarray:
    """T_world_obj of the model frame from the body's pose, snapped (rotation to 2^-30, translation to
    2^-24 m): the scene's stored source of truth."""
    pos, quat = pb.getBasePositionAndOrientation(body, physicsClientId=cid)
    T = np.eye(4)
    T[:3, :3] = R = np.asarray(pb.getMatrixFromQuaternion(quat)).reshape(3, 3)
    T[:3, 3] = np.asarray(pos) - (R * com).sum(1)  # no BLAS: see selfseg.generate.determinism
    return snap_pose(T)


def _simulate(bodies: list[CollisionBody], files: list[Path], rng: np.random.Generator, cfg: PhysicsConfig) -> DropResult:
    cid = pb.connect(pb.DIRECT)
    try:
        pb.setGravity(0, 0, -9.81, physicsClientId=cid)
        pb.setPhysicsEngineParameter(fixedTimeStep=cfg.time_step_s, numSolverIterations=cfg.solver_iterations,
                                     deterministicOverlappingPairs=1, physicsClientId=cid)
        h = cfg.table_half_extent_m
        table_shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[h, h, 0.025], physicsClientId=cid)
        table = pb.createMultiBody(0, table_shape, basePosition=[0, 0, -0.025], physicsClientId=cid)
        pb.changeDynamics(table, -1, lateralFriction=cfg.lateral_friction, physicsClientId=cid)
        ids: dict[int, int] = {}
        removed: list[int] = []
        steps = 0

        def step(still: dict[int, int]) -> None:
            """One simulation step; bodies that fell below the table are removed."""
            nonlocal steps
            pb.stepSimulation(physicsClientId=cid)
            steps += 1
            for i, body in list(ids.items()):
                if pb.getBasePositionAndOrientation(body, physicsClientId=cid)[0][2] < -0.2:
                    pb.removeBody(body, physicsClientId=cid)
                    del ids[i]
                    still.pop(i, None)
                    removed.append(i)
                    continue
                lin, ang = pb.getBaseVelocity(body, physicsClientId=cid)
                calm = math.hypot(*lin) < cfg.settle_linear_mps and math.hypot(*ang) < cfg.settle_angular_radps
                still[i] = still.get(i, 0) + 1 if calm else 0

        # Objects enter one at a time just above the pile, so that none falls from far.
        for i, (b, f) in enumerate(zip(bodies, files)):
            start = _start_position(cid, b.radius, ids, rng, cfg)
            shape = pb.createCollisionShape(pb.GEOM_MESH, fileName=str(f), physicsClientId=cid)
            ids[i] = pb.createMultiBody(b.mass, shape, basePosition=start, baseOrientation=_random_rotation(rng),
                                        physicsClientId=cid)
            pb.changeDynamics(ids[i], -1, lateralFriction=cfg.lateral_friction, rollingFriction=cfg.rolling_friction,
                              spinningFriction=cfg.spinning_friction, linearDamping=cfg.linear_damping,
                              angularDamping=cfg.angular_damping, physicsClientId=cid)
            for _ in range(cfg.drop_interval_steps):
                step({})
        for _phase in range(cfg.settle_phases):
            still: dict[int, int] = {}
            for _ in range(cfg.max_steps):
                step(still)
                if len(still) == len(ids) and all(s >= cfg.settle_steps for s in still.values()):
                    break
            off = [i for i, body in ids.items() if _off_table(cid, body, bodies[i], h)]
            unsettled = [i for i in ids if still[i] < cfg.settle_steps and i not in off]
            for i in off + unsettled:
                pb.removeBody(ids.pop(i), physicsClientId=cid)
            removed += off + unsettled
            if not unsettled:  # removing resting objects that hang off the edge disturbs nothing else
                break
        poses = {i: _pose(cid, body, bodies[i].com) for i, body in sorted(ids.items())}
        dist = _distances(cid, ids, table, cfg.contact_distance_m)
        deep = {k: -d for k, d in dist.items() if -d > cfg.penetration_report_m}
        return DropResult(poses=poses, removed=sorted(removed), attempts=1, steps=steps,
                          max_penetration_m=max([0.0] + [-d for d in dist.values()]), penetrations=deep,
                          contacts=sorted(dist))
    finally:
        pb.disconnect(physicsClientId=cid)


def _off_table(cid: int, body: int, b: CollisionBody, half_extent: float) -> bool:
    """True if the body's centre is outside the table top or any of its pieces reaches below it."""
    pos, quat = pb.getBasePositionAndOrientation(body, physicsClientId=cid)
    R = np.asarray(pb.getMatrixFromQuaternion(quat)).reshape(3, 3)
    lowest = min(float((v @ R[2]).min()) for v, _ in b.pieces) + pos[2]
    return bool(max(abs(pos[0]), abs(pos[1])) > half_extent or lowest < -0.01)


def _distances(cid: int, ids: dict[int, int], table: int, within: float) -> dict[tuple[int, int], float]:
    """Closest signed distance (m, negative = penetration) of every pair of bodies closer than
    ``within``, including each body against the table (as TABLE_ID)."""
    out = {}
    items = sorted(ids.items())
    pairs = [((TABLE_ID, table), (i, bi)) for i, bi in items]
    pairs += [(items[a], items[b]) for a in range(len(items)) for b in range(a + 1, len(items))]
    for (i, bi), (j, bj) in pairs:
        pts = pb.getClosestPoints(bi, bj, distance=within, physicsClientId=cid)
        if pts:
            out[(i, j)] = float(min(p[8] for p in pts))
    return out


def _collision_files(bodies: list[CollisionBody], folder: Path) -> list[Path]:
    """One OBJ per body with its convex pieces (pybullet builds a compound of their hulls)."""
    files = []
    for b in bodies:
        text = _obj_text(b.pieces)
        path = folder / f"collision_{hashlib.sha256(text.encode()).hexdigest()[:16]}.obj"
        if not path.exists():
            atomic_write_text(path, text)
        files.append(path)
    return files


def drop_objects(objects: list[ObjectModel], seed: int, cfg: PhysicsConfig = PhysicsConfig(),
                 cache_dir: Path | None = None, min_kept: int | None = None) -> DropResult:
    """Drop ``objects`` in random orientations onto the table and simulate until they rest.

    Objects that leave the table or never settle are removed. If fewer than ``min_kept`` remain,
    the scene is dropped again with a new sub-seed, at most ``cfg.max_attempts`` times. The same
    ``seed`` (and objects and config) gives identical poses. ``cache_dir`` keeps VHACD
    decompositions and collision files between calls.
    """
    if not objects:
        raise ValueError("drop_objects: no objects to drop")
    if min_kept is not None and not 0 <= min_kept <= len(objects):
        raise ValueError(f"drop_objects: min_kept={min_kept} must be between 0 and the {len(objects)} objects")
    with tempfile.TemporaryDirectory(prefix="selfseg_physics_") as tmp:
        folder = Path(cache_dir) if cache_dir is not None else Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        bodies = [collision_body(o, cfg, cache_dir) for o in objects]
        files = _collision_files(bodies, folder)
        for attempt in range(cfg.max_attempts):
            result = _simulate(bodies, files, np.random.default_rng([seed, attempt]), cfg)
            if min_kept is None or len(result.poses) >= min_kept:
                result.attempts = attempt + 1
                return result
    raise RuntimeError(f"drop_objects: fewer than {min_kept} of {len(objects)} objects stayed on the table in "
                       f"{cfg.max_attempts} drops (seed {seed}); enlarge the table or drop fewer objects")
