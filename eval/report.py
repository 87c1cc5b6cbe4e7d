"""``inspect``: one self-contained HTML report of a results folder, the paper's Figs. 3–5 in 3-D.

    inspect RESULTS [--dataset NAME] --out report.html [--max-points 3000]

``RESULTS`` is what ``evaluate --out`` / ``evaluate3d --out`` wrote (layout: :mod:`selfseg.eval.layout`), or
one dataset's folder in it (``RESULTS/scores/<dataset>``). The report (plotly; plotly.js embedded once, so the
file opens offline in any browser) shows for one dataset:

- **Scenes**, from ``evaluate3d``'s run (``RESULTS/work/ours/<dataset>/foldall`` and its per-video stages): each
  reconstructed cloud coloured by RGB, by LCCP + SymSeg segment (with the segment graph: nodes at segment
  centroids, edges between neighbouring segments), by object pseudo-label after matching (with the
  within-scene merge edges) and by ground-truth instance, side by side. Points are in the reconstruction's
  world frame (metres; the first camera's frame with estimated poses), at most ``--max-points`` per cloud
  (a deterministic subsample), stored as float32.
- **Matches**: every non-empty match of ``matches.json`` as its source and target components, each matched
  node pair in a colour of its own (other points grey), with the registration and every node pair's
  precision, recall and decision; and each match's outcome (``merged`` = accepted, else its pruning reason),
  counted as in ``diagnostics.json``.
- Tables I–III, the IoU plot and the montage of every 2-D run, as in the leaderboard
  (:mod:`selfseg.eval.leaderboard`).

One scene and one match are drawn at a time (buttons switch them): a browser keeps about 16 WebGL contexts
per page and every 3-D panel takes one. Ground truth is read (an inspection tool, not the method). Bad input
(not a results folder, a missing stage file) prints one line naming the file and exits with status 2.
"""
from __future__ import annotations

import argparse
import base64
import html
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from selfseg.config import ConfigError, from_dict
from selfseg.dataset import Dataset, DatasetError
from selfseg.eval.aggregate import fmt
from selfseg.eval.layout import SCORES_DIR
from selfseg.eval.leaderboard import TABLES_NOTE, bar_chart, load_results, montage, palette, tables
from selfseg.eval.points import gt_point_labels
from selfseg.eval.table2 import alignment, table2_pipeline
from selfseg.fileio import FileFormatError, atomic_write_text, read_json
from selfseg.method.pipeline import LABELS_NPY, SEGMENTS_NPZ, OursConfig
from selfseg.method.pseudolabels import DIAGNOSTICS_JSON, MATCHES_JSON, match_outcome
from selfseg.method.recon_stage import load_recon
from selfseg.method.segment_graph import SegmentGraph
from selfseg.poses import transform_points

MAX_POINTS = 3000  # points drawn per scene cloud
MATCH_POINTS = 800  # points drawn per side of a match
MATCH_FIGURES = 20  # matches drawn per outcome (the first ones in matches.json); every match is listed
MATCH_ROW = "ours-matching"  # the Table II row whose evaluate3d run the scenes and matches come from
SCENE_ROWS = ("lccp", "lccp+symseg", "ours-matching", "gt-merging")  # Table II rows whose per-scene IoU is listed
GREY = "#b4b4b4"  # points without a label, and unmatched points of a match
PANEL_HEIGHT_PX = 460
SCRIPT = """
function showFigure(group, id) {
  var box = document.getElementById(group + "-view");
  Plotly.purge(box);
  var fig = JSON.parse(document.getElementById(id).textContent);
  Plotly.newPlot(box, fig.data, fig.layout, {displaylogo: false, responsive: true});
  document.querySelectorAll("button[data-group='" + group + "']").forEach(function (b) {
    b.classList.toggle("active", b.getAttribute("data-fig") === id);
  });
}
document.addEventListener("DOMContentLoaded", function () {
  document.querySelectorAll("button[data-fig]").forEach(function (b) {
    b.addEventListener("click", function () { showFigure(b.getAttribute("data-group"), b.getAttribute("data-fig")); });
  });
  document.querySelectorAll("div.view[data-initial]").forEach(function (v) {
    showFigure(v.id.replace(/-view$/, ""), v.getAttribute("data-initial"));
  });
});
"""
STYLE = """
body { font-family: sans-serif; margin: 1em 2em; color: #222; }
table { border-collapse: collapse; margin: .5em 0 1em; font-size: 90%; }
td, th { border: 1px solid #ccc; padding: 2px 6px; text-align: left; vertical-align: top; }
button { margin: 1px; cursor: pointer; }
button.active { background: #4c72b0; color: white; }
div.view { width: 100%; min-height: 300px; border: 1px solid #ddd; }
img { max-width: 100%; }
"""


@dataclass
class SceneView:
    """One reconstructed scene (world frame of the reconstruction, metres) and its labels per point."""

    video_id: str
    points_w: np.ndarray  # N×3
    colors: np.ndarray  # N×3 in [0, 1]
    pseudo: np.ndarray  # N object pseudo-labels after matching (−1 none)
    graph: SegmentGraph  # LCCP + SymSeg segments (graph.labels: N, −1 none), centroids, edges
    shown: np.ndarray  # indices of the points drawn (sorted)
    gt_shown: np.ndarray  # GT instance id of the points drawn (0 = no object within the scoring distance)
    up: np.ndarray  # unit normal of the support plane, pointing up
    camera_w: np.ndarray  # position of the first posed camera


def subsample(n: int, max_points: int, seed: int = 0) -> np.ndarray:
    """Sorted indices of at most ``max_points`` of ``n`` points (deterministic)."""
    if n <= max_points:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False))


def load_scenes(results: Path, record: dict, max_points: int, models: dict | None = None
                ) -> tuple[list[SceneView], dict, dict]:
    """The scenes, ``matches.json`` and ``diagnostics.json`` of the ``evaluate3d`` run that wrote ``record`` (its
    ours-matching result). ``models`` ({video_id: {obj_id: mesh in metres}}) replaces the dataset's model
    files for the ground truth (analytic test scenes have none)."""
    dataset = Dataset(record["dataset"]["root"])
    method = table2_pipeline(dataset, from_dict(OursConfig, record["config"], "config"), results)
    pseudo_dir = method.pseudo_dir()
    matches, diagnostics = read_json(pseudo_dir / MATCHES_JSON), read_json(pseudo_dir / DIAGNOSTICS_JSON)
    cache = method.stage_cache([dataset.video(v) for v in matches["scenes"]])
    scenes = []
    for vid in matches["scenes"]:
        rec = load_recon(cache.path("recon", vid))
        graph = SegmentGraph.load(cache.path("overseg", vid) / SEGMENTS_NPZ)
        labels_path = pseudo_dir / LABELS_NPY.format(video_id=vid)
        pseudo = np.load(labels_path)
        if not len(pseudo) == len(graph.labels) == len(rec.points_w):
            raise FileFormatError(f"{labels_path}: {len(pseudo)} pseudo-labels and {len(graph.labels)} segment labels "
                                  f"for the {len(rec.points_w)} points of {rec.dir}")
        shown = subsample(len(rec.points_w), max_points)
        T_gtworld_world, _ = alignment(rec, dataset.labeled(vid))
        gt = gt_point_labels(transform_points(rec.points_w[shown], T_gtworld_world), dataset, vid,
                             record["options"]["max_dist_m"], None if models is None else models[vid])
        scenes.append(SceneView(vid, rec.points_w, rec.colors, pseudo, graph, shown, gt, rec.plane[:3],
                                rec.T_world_cam[min(rec.T_world_cam)][:3, 3]))
    return scenes, matches, diagnostics


def _hex(rgb: np.ndarray) -> np.ndarray:
    return np.array([f"#{r:02x}{g:02x}{b:02x}" for r, g, b in np.asarray(rgb, np.uint8)])


def label_colours(ids: np.ndarray) -> list[str]:
    """Colour per id: 0 grey, id ≥ 1 the leaderboard montage's colour of that id."""
    ids = np.asarray(ids, np.int64)
    cols = _hex(palette(int(ids.max(initial=0))))
    cols[0] = GREY
    return cols[ids].tolist()


def _xyz(points: np.ndarray) -> dict:
    p = np.asarray(points, np.float32)
    return {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]}


def _lines(points: np.ndarray, pairs: np.ndarray) -> dict:
    """x, y, z lists drawing a segment per pair of point indices (None between segments)."""
    out: dict = {"x": [], "y": [], "z": []}
    for i, j in np.asarray(pairs, np.int64).reshape(-1, 2):
        for axis, key in enumerate("xyz"):
            out[key] += [round(float(points[i, axis]), 4), round(float(points[j, axis]), 4), None]
    return out


def _camera(points: np.ndarray, up: np.ndarray, camera_w: np.ndarray) -> dict:
    """A plotly scene camera looking at the cloud from the side of the recording camera, ``up`` up (all in the
    reconstruction's world frame: points and camera position in m, ``up`` a unit vector)."""
    view = camera_w - points.mean(0) if len(points) else np.array([0.0, 0.0, -1.0])
    view = view / max(np.linalg.norm(view), 1e-9) + 0.5 * up
    eye = 2.0 * view / max(np.linalg.norm(view), 1e-9)
    return {"up": dict(zip("xyz", map(float, up))), "eye": dict(zip("xyz", map(float, eye)))}


def _figure(traces: list[list], titles: list[str], cameras: list[dict]):
    """One row of 3-D panels; ``traces[i]`` are the traces of panel i."""
    from plotly.subplots import make_subplots

    fig = make_subplots(rows=1, cols=len(titles), specs=[[{"type": "scene"}] * len(titles)], subplot_titles=titles,
                        horizontal_spacing=0.01)
    for col, panel in enumerate(traces, 1):
        for t in panel:
            fig.add_trace(t, row=1, col=col)
    hidden = {"visible": False}
    for i, cam in enumerate(cameras, 1):
        fig.layout[f"scene{i if i > 1 else ''}"].update(aspectmode="data", camera=cam, xaxis=hidden, yaxis=hidden,
                                                         zaxis=hidden)
    fig.update_layout(template="none", height=PANEL_HEIGHT_PX, showlegend=False,
                      margin={"l": 0, "r": 0, "t": 30, "b": 0})
    return fig


def scene_figure(s: SceneView, merge_edges: list[list[int]]):
    """RGB | LCCP + SymSeg segments with the segment graph | pseudo-labels with merge edges | ground truth."""
    import plotly.graph_objects as go

    pts = s.points_w[s.shown]
    seg = s.graph.labels[s.shown]
    cloud = lambda colours, opacity=1.0: go.Scatter3d(  # noqa: E731
        mode="markers", marker={"size": 2, "color": colours, "opacity": opacity}, hoverinfo="skip", **_xyz(pts))
    seg_colours = label_colours(np.arange(s.graph.n_segments + 1))
    nodes = go.Scatter3d(mode="markers", marker={"size": 5, "color": seg_colours[1:], "line": {"color": "black",
                                                                                               "width": 1}},
                         text=[f"segment {i}: {n} points" for i, n in enumerate(s.graph.sizes)], hoverinfo="text",
                         **_xyz(s.graph.centroids))
    edges = go.Scatter3d(mode="lines", line={"color": "black", "width": 3}, hoverinfo="skip",
                         **_lines(s.graph.centroids, s.graph.edges))
    merges = go.Scatter3d(mode="lines", line={"color": "red", "width": 6}, hoverinfo="skip",
                          **_lines(s.graph.centroids, np.asarray(merge_edges, np.int64)))
    panels = [[cloud(_hex(np.clip(s.colors[s.shown] * 255, 0, 255)).tolist())],
              [cloud([seg_colours[i] for i in seg + 1], 0.3), edges, nodes],  # the graph shows through
              [cloud(label_colours(s.pseudo[s.shown] + 1)), merges],
              [cloud(label_colours(s.gt_shown))]]
    titles = ["RGB", f"LCCP + SymSeg: {s.graph.n_segments} segments, {len(s.graph.edges)} edges",
              "pseudo-labels after matching (red: merges)", "ground truth"]
    return _figure(panels, titles, [_camera(pts, s.up, s.camera_w)] * 4)


def match_figure(m: dict, src: SceneView, tgt: SceneView, max_points: int):
    """The match's source and target components; node pair p (i → k) in colour p + 1 in both, other points grey."""
    import plotly.graph_objects as go

    pair_colour = label_colours(np.arange(len(m["pairs"]) + 1))[1:]
    panels, cameras = [], []
    for scene, comp, side in ((src, m["src_comp"], "src"), (tgt, m["tgt_comp"], "tgt")):
        segments = scene.graph.components()[comp]
        idx = np.nonzero(np.isin(scene.graph.labels, segments))[0]
        idx = idx[subsample(len(idx), max_points)]
        colour = np.full(len(idx), GREY, dtype=object)
        for p, pair in enumerate(m["pairs"]):
            colour[scene.graph.labels[idx] == pair[side]] = pair_colour[p]
        nodes = [pair[side] for pair in m["pairs"]]
        text = [f"{pair['src']} → {pair['tgt']}: {pair['reason']}, P {fmt(pair['precision'])} R {fmt(pair['recall'])}"
                for pair in m["pairs"]]
        panels.append([
            go.Scatter3d(mode="markers", marker={"size": 2, "color": colour.tolist()}, hoverinfo="skip",
                         **_xyz(scene.points_w[idx])),
            go.Scatter3d(mode="markers", text=text, hoverinfo="text",
                         marker={"size": 6, "color": pair_colour, "line": {"color": "black", "width": 1},
                                 "symbol": ["diamond" if pair["accepted"] else "x" for pair in m["pairs"]]},
                         **_xyz(scene.graph.centroids[nodes]))])
        cameras.append(_camera(scene.points_w[idx], scene.up, scene.camera_w))
    titles = [f"source {m['src_scene']}, component {m['src_comp']}", f"target {m['tgt_scene']}, component {m['tgt_comp']}"]
    return _figure(panels, titles, cameras)


def _figure_json(fig, element_id: str) -> str:
    """The figure as a JSON script element (``</`` escaped so that no string ends the element)."""
    return (f'<script type="application/json" id="{element_id}">' + fig.to_json().replace("</", "<\\/") + "</script>")


def md_inline(text: str) -> str:
    """HTML of the leaderboard's markdown inline marks (**bold**, *italic*, `code`)."""
    t = html.escape(text)
    t = re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", t)
    t = re.sub(r"\*(.+?)\*", r"<i>\1</i>", t)
    return re.sub(r"`(.+?)`", r"<code>\1</code>", t)


def md_table(lines: list[str]) -> str:
    """HTML of a markdown table (first row the header; the |---| row dropped)."""
    rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in lines
            if not set(line.strip()) <= set("|-")]
    head = "".join(f"<th>{md_inline(c)}</th>" for c in rows[0])
    body = "".join("<tr>" + "".join(f"<td>{md_inline(c)}</td>" for c in r) + "</tr>" for r in rows[1:])
    return f"<table><tr>{head}</tr>{body}</table>"


def _table(head: list[str], rows: list[list[str]]) -> str:
    """HTML table; cells are HTML already."""
    return ("<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>"
            + "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows) + "</table>")


def _png(data: bytes | None, alt: str) -> str:
    if data is None:
        return f"<p>({html.escape(alt)} not built: the dataset folder recorded in the results is not available)</p>"
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(data).decode()}">'


def _button(group: str, fig_id: str, label: str) -> str:
    return f'<button data-group="{group}" data-fig="{fig_id}">{html.escape(label)}</button>'


def scenes_section(scenes: list[SceneView], diagnostics: dict, groups: dict) -> str:
    """Per scene: a table row (counts, Table II IoU per row) and its figure's JSON; the view shows the first."""
    rows_3d = [r for r in SCENE_ROWS if ("3d", r) in groups]
    rows, figs = [], []
    for s in scenes:
        d = diagnostics["scenes"][s.video_id]
        ious = [fmt(groups["3d", r][0]["per_video"].get(s.video_id, {}).get("IoU")) for r in rows_3d]
        rows.append([f'<span id="scene-{s.video_id}"></span>' + _button("scenes", f"fig-scene-{s.video_id}", s.video_id),
                     f"{len(s.shown)} of {len(s.points_w)}", str(d["segments"]), str(len(s.graph.edges)),
                     str(d["components"]), str(d["objects"]), str(d["merges"]), *ious])
        figs.append(_figure_json(scene_figure(s, diagnostics["merges"]["within"][s.video_id]), f"fig-scene-{s.video_id}"))
    head = ["scene", "points drawn", "segments", "graph edges", "components", "objects after matching", "merges",
            *(f"IoU {r}" for r in rows_3d)]
    return ("<h2>Scenes</h2><p>Each reconstructed cloud (world frame of the reconstruction, m) coloured by RGB, by "
            "LCCP + SymSeg segment with the segment graph (nodes at segment centroids, edges between neighbours), by "
            "object pseudo-label after matching (red: within-scene merge edges) and by ground-truth instance (grey: "
            "no label). Drag to rotate; the buttons switch scenes.</p>" + _table(head, rows)
            + f'<div id="scenes-view" class="view" data-initial="fig-scene-{scenes[0].video_id}"></div>' + "".join(figs))


def drawn_matches(outcomes: list[str], per_outcome: int) -> list[bool]:
    """Which matches get a figure: the first ``per_outcome`` of each outcome, in order."""
    seen: dict[str, int] = {}
    drawn = []
    for o in outcomes:
        seen[o] = seen.get(o, 0) + 1
        drawn.append(seen[o] <= per_outcome)
    return drawn


def matches_section(scenes: list[SceneView], matches: dict, diagnostics: dict, match_points: int,
                    match_figures: int) -> str:
    """The matching and pruning counts of ``diagnostics.json``, a row per match with its outcome, and the figures
    of the first ``match_figures`` matches of each outcome (``match_points`` points per side)."""
    by_id = {s.video_id: s for s in scenes}
    outcomes = [match_outcome(len(m["merged_edges"]), [p["reason"] for p in m["pairs"] if not p["accepted"]])
                for m in matches["matches"]]
    drawn = drawn_matches(outcomes, match_figures)
    rows, figs = [], []
    for n, (m, outcome) in enumerate(zip(matches["matches"], outcomes)):
        reg = m["registration"] or {}
        reg_text = "—" if not reg else (html.escape(reg["error"]) if "error" in reg else
                                        f"fitness {fmt(reg['fitness'])}, RMSE {1000 * reg['rmse']:.1f} mm")
        pairs = "<br>".join(f"{p['src']} → {p['tgt']}: {html.escape(p['reason'])}"
                            + ("" if p["precision"] is None else f" (P {fmt(p['precision'])}, R {fmt(p['recall'])})")
                            for p in m["pairs"])
        label = _button("matches", f"fig-match-{n}", f"match {n}") if drawn[n] else f"match {n} (not drawn)"
        rows.append([f'<span id="match-{n}"></span>' + label,
                     f"{m['src_scene']} / {m['src_comp']}", f"{m['tgt_scene']} / {m['tgt_comp']}",
                     fmt(m["J"]), fmt(m["T1"]), f"<b>{outcome}</b>" if outcome == "merged" else html.escape(outcome),
                     str(len(m["merged_edges"])), reg_text, pairs])
        if drawn[n]:
            figs.append(_figure_json(match_figure(m, by_id[m["src_scene"]], by_id[m["tgt_scene"]], match_points),
                                     f"fig-match-{n}"))
    pr = diagnostics["pruning"]
    counts = _table(["", *pr["matches_by_outcome"]], [["matches (diagnostics.json)",
                                                       *map(str, pr["matches_by_outcome"].values())]])
    reasons = _table(["", *pr["node_pairs_by_reason"]], [["node pairs", *map(str, pr["node_pairs_by_reason"].values())]])
    stats = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in diagnostics["matching"].items())
    out = (f"<h2>Matches across scenes</h2><p>Mode <code>{html.escape(diagnostics['mode'])}</code>; {stats or 'no graph matching'}. "
           "A match is accepted (<b>merged</b>) when an edge of the source maps onto an edge of the target with both "
           "node pairs accepted; otherwise its outcome is the first pruning criterion that rejected its node pairs "
           "(criterion 1: cost_above_T1; 2: no_mapped_edge, registration_failed, precision_recall; 3: isolation).</p>"
           + counts + reasons)
    if not rows:
        return out + "<p>No non-empty match.</p>"
    first = next((n for n, o in enumerate(outcomes) if o == "merged" and drawn[n]), 0)
    cap = (f"<p>{sum(drawn)} of {len(drawn)} matches are drawn: the first {match_figures} of each outcome "
           f"(<code>inspect --match-figures</code> draws more); the others are listed.</p>"
           if not all(drawn) else "")
    head = ["match", "source scene / component", "target scene / component", "J", "T1", "outcome", "merged edges",
            "registration", "node pairs (source → target segment: decision, precision, recall)"]
    return (out + "<p>Each match: its source and target components, a colour per matched node pair (diamond: "
            "accepted, x: rejected), other points grey.</p>" + cap + _table(head, rows)
            + (f'<div id="matches-view" class="view" data-initial="fig-match-{first}"></div>' if figs else "")
            + "".join(figs))


def leaderboard_section(groups: dict, results: Path, dataset: str) -> str:
    """Tables I–III, the IoU plot and the montage, as :mod:`selfseg.eval.leaderboard` makes them."""
    parts = [f"<h2>{md_inline(title)}</h2>" + md_table(lines) for title, lines in tables(groups, dataset)]
    return (f"<p>{md_inline(TABLES_NOTE)}</p>" + parts[0]
            + _png(bar_chart(groups, f"IoU per method: {dataset}"), "IoU per method") + "".join(parts[1:])
            + "<h2>Qualitative (2-D)</h2>" + _png(montage(groups, results), "RGB, ground truth and predictions"))


def render(results: Path, dataset: str, groups: dict, max_points: int = MAX_POINTS, models: dict | None = None,
           match_points: int = MATCH_POINTS, match_figures: int = MATCH_FIGURES) -> str:
    """The report's HTML (plotly.js embedded once, no external resource)."""
    from plotly.offline import get_plotlyjs

    record = groups.get(("3d", MATCH_ROW))
    if record is None:
        body = ("<h2>Scenes</h2><p>No <code>evaluate3d</code> run with the ours-matching row in these results: run "
                "<code>evaluate3d --data DATA --out RESULTS</code> to see the reconstructed scenes and matches.</p>")
    else:
        scenes, matches, diagnostics = load_scenes(results, record[0], max_points, models)
        body = (scenes_section(scenes, diagnostics, groups)
                + matches_section(scenes, matches, diagnostics, match_points, match_figures))
    title = f"selfseg report: {dataset}"
    return (f'<!DOCTYPE html><html><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
            f"<style>{STYLE}</style><script>{get_plotlyjs()}</script><script>{SCRIPT}</script></head><body>"
            f"<h1>{html.escape(title)}</h1><p>Results: <code>{html.escape(str(results))}</code></p>"
            + body + leaderboard_section(groups, results, dataset) + "</body></html>\n")


def write_report(results: str | Path, out: str | Path, dataset: str | None = None, max_points: int = MAX_POINTS,
                 models: dict | None = None, match_points: int = MATCH_POINTS, match_figures: int = MATCH_FIGURES) -> Path:
    """Write the report of ``dataset`` (the folder name under ``RESULTS/scores``; may be omitted when there is one)."""
    for flag, value, least in (("--max-points", max_points, 1), ("--match-points", match_points, 1),
                               ("--match-figures", match_figures, 0)):
        if value < least:
            raise ConfigError(f"{flag} must be ≥ {least}, got {value}")
    results = Path(results)
    if results.parent.name == SCORES_DIR and dataset is None:  # RESULTS/scores/<dataset>
        results, dataset = results.parent.parent, results.name
    if not (results / SCORES_DIR).is_dir():
        raise FileNotFoundError(f"{results / SCORES_DIR}: not a results folder (run evaluate or evaluate3d first)")
    found = load_results(results)
    if dataset is None and len(found) != 1:
        raise ConfigError(f"{results / SCORES_DIR}: results of {len(found)} datasets ({', '.join(found) or 'none'}); "
                          "choose one with --dataset")
    dataset = dataset if dataset is not None else next(iter(found))
    if dataset not in found:
        raise ConfigError(f"--dataset {dataset!r}: no results in {results / SCORES_DIR} (found: "
                          f"{', '.join(found) or 'none'})")
    atomic_write_text(out, render(results, dataset, found[dataset], max_points, models, match_points, match_figures))
    return Path(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="inspect", description="Write one self-contained HTML report (3-D scenes, "
                                "segment graphs, matches, Tables I–III) of a results folder.")
    p.add_argument("results", type=Path, metavar="RESULTS",
                   help="results folder of evaluate/evaluate3d --out, or one dataset's RESULTS/scores/<dataset>")
    p.add_argument("--dataset", help="the dataset (folder name under RESULTS/scores/) when there are several")
    p.add_argument("--out", type=Path, required=True, help="the HTML file to write")
    p.add_argument("--max-points", type=int, default=MAX_POINTS,
                   help=f"points drawn per scene cloud (default {MAX_POINTS})")
    p.add_argument("--match-points", type=int, default=MATCH_POINTS,
                   help=f"points drawn per side of a match (default {MATCH_POINTS})")
    p.add_argument("--match-figures", type=int, default=MATCH_FIGURES,
                   help=f"matches drawn per outcome, the first ones; every match is listed (default {MATCH_FIGURES})")
    args = p.parse_args(argv)
    try:
        print(write_report(args.results, args.out, args.dataset, args.max_points, match_points=args.match_points,
                           match_figures=args.match_figures))
    except (ConfigError, DatasetError, FileFormatError, FileNotFoundError) as e:
        print(f"inspect: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
