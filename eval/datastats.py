"""Data statistics: how close a dataset and its over-segmentation are to the paper's setting.

The paper's Table II LCCP row (P .984, R .771 on its synthetic scenes) is a property of the data and the
over-segmentation, not of any learning: LCCP almost never joins two objects there and mostly splits
objects into parts, which graph matching then joins. ``evaluate3d --stats`` measures, per scene and
overall:

- ``touching_pairs``: pairs of GT objects whose meshes (at their GT poses) come within
  :data:`TOUCH_DIST_M` of each other (contact is what makes LCCP join objects);
- P/R/IoU of the ``lccp`` and ``lccp+symseg`` rows and of the ``gt-merging`` ceiling (Table II metrics);
- per object, for the ``lccp`` and ``lccp+symseg`` rows: segments of its own (segments whose majority GT
  instance it is), whether it is split into ≥ 2 or has none, and where the recall it loses goes
  (:func:`object_breakdown`): ``pruned`` (points without a segment), ``other`` (in segments that belong
  to another object), ``own_parts`` (in its own other segments: the only loss merging can recover);
- reconstruction: distance of every reconstructed point to the nearest GT object surface, and the share
  of the GT object surfaces that a reconstructed point comes within :data:`COVER_DIST_M` of (this counts
  surfaces no camera sees, such as bottoms, as uncovered);
- camera distance to the orbit centre (m) and object size in pixels (the larger side of each visible
  instance's bounding box in the ground-truth masks of every :data:`MASK_FRAME_STRIDE`-th frame).

All points are in the dataset's world frame (metres). Functions here read ground truth; they are
evaluation code, never part of a method.
"""
from __future__ import annotations

import numpy as np

from selfseg.dataset import Dataset
from selfseg.eval.merges import segment_instances, summary
from selfseg.eval.metrics import segment_metrics
from selfseg.raycast import RaycastScene

TOUCH_DIST_M = 0.005  # GT meshes closer than this touch
COVER_DIST_M = 0.005  # a GT surface sample is covered when a reconstructed point is this close
ARTIFACT_DIST_M = 0.01  # reconstructed points farther than this from every GT object surface are artifacts
SURFACE_SAMPLE_M2 = 2e-6  # one surface sample per 2 mm² (spacing ~1.4 mm) for distances between meshes
MASK_FRAME_STRIDE = 10  # object sizes in pixels from every n-th frame (the test frames' stride)
LOSS_KEYS = ("pruned", "other", "own_parts")
BREAKDOWN_ROWS = ("lccp", "lccp+symseg")


def sample_surface(vertices: np.ndarray, faces: np.ndarray, per_m2: float = 1.0 / SURFACE_SAMPLE_M2,
                   seed: int = 0) -> np.ndarray:
    """Area-uniform points on a triangle mesh (m), plus its vertices; deterministic for a seed."""
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    n = max(int(np.ceil(area.sum() * per_m2)), 1)
    face = rng.choice(len(faces), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    flip = r1 + r2 > 1
    r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
    t = tri[face]
    pts = t[:, 0] + r1[:, None] * (t[:, 1] - t[:, 0]) + r2[:, None] * (t[:, 2] - t[:, 0])
    return np.concatenate([pts, vertices])


def mesh_distances(scene: RaycastScene) -> dict[tuple[int, int], float]:
    """Smallest distance (m) between every two meshes of ``scene``, keyed by their ids (i < j): each
    mesh's surface samples against the other mesh, both ways (error below the sample spacing)."""
    samples = [sample_surface(v, f) for v, f in zip(scene.vertices, scene.faces)]
    out = {}
    for a in range(len(scene.ids)):
        for b in range(a + 1, len(scene.ids)):
            d_ab = RaycastScene([scene.vertices[b]], [scene.faces[b]], [1]).closest(samples[a])[0].min()
            d_ba = RaycastScene([scene.vertices[a]], [scene.faces[a]], [1]).closest(samples[b])[0].min()
            i, j = sorted((scene.ids[a], scene.ids[b]))
            out[(i, j)] = float(min(d_ab, d_ba))
    return out


def touching_pairs(scene: RaycastScene, max_dist_m: float = TOUCH_DIST_M) -> list[tuple[int, int]]:
    """Id pairs (i < j) of meshes that come within ``max_dist_m`` of each other."""
    return sorted(pair for pair, d in mesh_distances(scene).items() if d <= max_dist_m)


def object_breakdown(pred: np.ndarray, gt: np.ndarray) -> dict[int, dict]:
    """Per GT object (id ≥ 1 in ``gt``; 0 = no object) of a point segmentation ``pred`` (segment ids ≥ 0,
    −1 = none): its points, own segments (majority instance = it), the segment the paper's Hungarian
    matching gives it, and how its points divide: ``recall`` (in the matched segment) + ``pruned`` +
    ``other`` (segments whose majority is another object or no object) + ``own_parts`` = 1."""
    pred, gt = np.asarray(pred).ravel().astype(np.int64), np.asarray(gt).ravel().astype(np.int64)
    n_seg = int(pred.max(initial=-1)) + 1
    majority = segment_instances(pred, gt, n_seg)
    matches = segment_metrics(pred + 1, gt, return_matches=True)["matches"]  # {gt id: pred id (= segment + 1)}
    out = {}
    for obj in np.unique(gt[gt > 0]).tolist():
        mine = pred[gt == obj]
        matched = matches.get(obj, 0) - 1  # −1: unmatched
        own = np.flatnonzero(majority == obj)
        seg = mine[mine >= 0]
        n = len(mine)
        out[int(obj)] = {
            "points": n, "own_segments": len(own), "matched_segment": int(matched),
            "recall": float(np.sum(mine == matched) / n) if matched >= 0 else 0.0,
            "pruned": float(np.sum(mine < 0) / n),
            "other": float(np.sum((seg != matched) & (majority[seg] != obj)) / n),
            "own_parts": float(np.sum((seg != matched) & (majority[seg] == obj)) / n)}
    return out


def breakdown_summary(objects: list[dict]) -> dict:
    """Means over objects of :func:`object_breakdown` entries: own segments, split/none shares, losses."""
    if not objects:
        return {"objects": 0}
    own = np.array([o["own_segments"] for o in objects])
    return {"objects": len(objects), "segments_per_object": float(own.mean()),
            "split_share": float(np.mean(own >= 2)), "no_segment_share": float(np.mean(own == 0)),
            "no_segment": int(np.sum(own == 0)), "recall": float(np.mean([o["recall"] for o in objects])),
            **{f"lost_{k}": float(np.mean([o[k] for o in objects])) for k in LOSS_KEYS}}


def reconstruction_stats(points_w: np.ndarray, scene: RaycastScene) -> dict:
    """Distance (mm) of reconstructed points to the nearest GT object surface, share of artifacts (farther
    than :data:`ARTIFACT_DIST_M`) and surface coverage (share of GT surface samples within
    :data:`COVER_DIST_M` of a reconstructed point)."""
    from scipy.spatial import cKDTree

    dist, _ = scene.closest(points_w)
    surface = np.concatenate([sample_surface(v, f, per_m2=1.0 / 4e-6) for v, f in zip(scene.vertices, scene.faces)])
    covered = cKDTree(points_w).query(surface, distance_upper_bound=COVER_DIST_M)[0] <= COVER_DIST_M
    return {"points": int(len(points_w)), "error_median_mm": float(np.median(dist) * 1000),
            "error_p90_mm": float(np.quantile(dist, 0.9) * 1000),
            "artifact_share": float(np.mean(dist > ARTIFACT_DIST_M)), "coverage": float(np.mean(covered))}


def view_stats(dataset: Dataset, video_id: str, frame_stride: int = MASK_FRAME_STRIDE) -> dict:
    """Camera distance to the orbit centre (m, every frame) and object size in pixels (larger bounding-box
    side of each visible instance, every ``frame_stride``-th frame)."""
    video = dataset.labeled(video_id)
    centre = np.asarray(video.scene_info["orbit"]["center"], dtype=np.float64) \
        if "orbit" in video.scene_info else None
    dist = [] if centre is None else [float(np.linalg.norm(video.T_world_cam(f)[:3, 3] - centre))
                                      for f in video.frame_ids]
    sizes = []
    for f in video.frame_ids[::frame_stride]:
        inst = video.inst(f)
        for k in np.unique(inst[inst > 0]):
            v, u = np.nonzero(inst == k)
            sizes.append(max(int(v.max() - v.min() + 1), int(u.max() - u.min() + 1)))
    return {"camera_distance_m": summary(dist), "object_px": summary(sizes)}


def scene_stats(points_w: np.ndarray, labels: dict[str, np.ndarray], gt_inst: np.ndarray, scene: RaycastScene,
                views: dict | None = None) -> dict:
    """Everything above for one reconstructed scene: ``points_w`` (N×3, dataset world, m), ``labels`` per
    row (segment per point, −1 = none), ``gt_inst`` (GT instance per point, 0 = none), the GT ``scene``."""
    rows = {}
    for row, lab in labels.items():
        m = segment_metrics(np.asarray(lab) + 1, gt_inst)
        rows[row] = {"P": m["P"], "R": m["R"], "IoU": m["IoU"], "segments": int(np.asarray(lab).max(initial=-1) + 1)}
    objects = {row: object_breakdown(labels[row], gt_inst) for row in BREAKDOWN_ROWS if row in labels}
    return {"objects": len(scene.ids), "touching_pairs": [list(p) for p in touching_pairs(scene)],
            "rows": rows, "per_object": {row: {str(k): v for k, v in o.items()} for row, o in objects.items()},
            "breakdown": {row: breakdown_summary(list(o.values())) for row, o in objects.items()},
            "reconstruction": reconstruction_stats(points_w, scene), **(views or {})}


def overall_stats(scenes: dict[str, dict]) -> dict:
    """Totals and means over scenes (Table II rows: mean over scenes; object stats: over all objects)."""
    vals = list(scenes.values())
    rows = sorted({r for s in vals for r in s["rows"]})
    out = {"scenes": len(vals), "objects": int(sum(s["objects"] for s in vals)),
           "touching_pairs": int(sum(len(s["touching_pairs"]) for s in vals)),
           "touching_pairs_per_scene": float(np.mean([len(s["touching_pairs"]) for s in vals])),
           "rows": {r: {k: float(np.mean([s["rows"][r][k] for s in vals if r in s["rows"]]))
                        for k in ("P", "R", "IoU", "segments")} for r in rows},
           "breakdown": {row: breakdown_summary([o for s in vals for o in s["per_object"].get(row, {}).values()])
                         for row in BREAKDOWN_ROWS if any(row in s["per_object"] for s in vals)}}
    rec = [s["reconstruction"] for s in vals]
    out["reconstruction"] = {k: float(np.mean([r[k] for r in rec]))
                             for k in ("error_median_mm", "error_p90_mm", "artifact_share", "coverage")}
    for key in ("camera_distance_m", "object_px"):  # the median of the scene medians, and their range
        med = [s[key]["median"] for s in vals if s.get(key, {}).get("median") is not None]
        if med:
            out[key] = {"median": float(np.median(med)), "lo": float(min(med)), "hi": float(max(med))}
    return out


STATS_HEAD = ["scene", "objs", "touch", "LCCP P", "R", "IoU", "+Sym P", "R", "IoU", "gt-merge", "segs/obj", "split",
              "none", "lost prune", "other", "own", "err mm", ">1cm", "cover", "cam m", "obj px"]


def stats_line(name: str, s: dict) -> list[str]:
    """One table line of a scene's statistics or of :func:`overall_stats` (touch: pairs, or mean per scene)."""
    r, b = s["rows"], s["breakdown"].get("lccp", {})
    f = lambda x: "–" if x is None or x != x else f"{x:.3f}"  # noqa: E731
    touch = s.get("touching_pairs_per_scene", len(s["touching_pairs"]) if isinstance(s["touching_pairs"], list) else 0)
    cam, px = s.get("camera_distance_m", {}), s.get("object_px", {})
    return [name, str(s["objects"]), f"{touch:.2g}",
            *(f(r.get(row, {}).get(k)) for row in ("lccp", "lccp+symseg") for k in ("P", "R", "IoU")),
            f(r.get("gt-merging", {}).get("IoU")), f"{b.get('segments_per_object', float('nan')):.2f}",
            f(b.get("split_share")), str(b.get("no_segment", "–")), *(f(b.get(f"lost_{k}")) for k in LOSS_KEYS),
            f"{s['reconstruction']['error_median_mm']:.1f}", f(s["reconstruction"]["artifact_share"]),
            f(s["reconstruction"]["coverage"]), "–" if cam.get("median") is None else f"{cam['median']:.2f}",
            "–" if px.get("median") is None else f"{px['median']:.0f}"]


def stats_table(lines: list[list[str]], first: str = "scene") -> str:
    """Right-aligned columns under :data:`STATS_HEAD` (its first heading replaced by ``first``)."""
    head = [first] + STATS_HEAD[1:]
    widths = [max(len(x) for x in col) for col in zip(head, *lines)]
    fmt = lambda cells: "  ".join(c.rjust(w) for c, w in zip(cells, widths))  # noqa: E731
    return "\n".join([fmt(head), *map(fmt, lines)])


def format_stats(stats: dict) -> str:
    """A table: one line per scene and one for all of them."""
    lines = [stats_line(v, s) for v, s in stats["scenes"].items()] + [stats_line("all", stats["overall"])]
    return (f"Data statistics of {stats['dataset']} (lccp columns: segments per object, split ≥ 2, objects with no "
            f"segment, recall lost; touch: pairs per scene)\n" + stats_table(lines))
