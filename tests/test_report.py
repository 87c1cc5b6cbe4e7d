"""The ``inspect`` report: one offline HTML file with every scene and match of a tiny run, and a real browser
(headless Chromium, no network) that draws its 3-D panels."""
import base64
import json
import re
import shutil
import subprocess
from collections import Counter

import numpy as np
import pytest

from selfseg.analytic import make_dataset, two_box_scenes
from selfseg.config import load_config
from selfseg.dataset import Dataset
from selfseg.eval.cli import main as evaluate
from selfseg.eval.layout import SCORES_DIR
from selfseg.eval.leaderboard import REPORT_HTML, build
from selfseg.eval.report import main, write_report
from selfseg.eval.table2 import run_table2, table2_pipeline
from selfseg.fileio import read_json
from selfseg.method.pipeline import OursConfig
from selfseg.method.pseudolabels import DIAGNOSTICS_JSON, MATCHES_JSON, match_outcome
from test_pipeline import FAST

MAX_POINTS = 1000
SIZE_BOUND = 7_000_000  # bytes: plotly.js (4.8 MB) and a tiny run's clouds


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A tiny run: two 2-D runs (one with fold 0 only) and evaluate3d's matching row on ray-cast two-box scenes."""
    root = tmp_path_factory.mktemp("report")
    scenes = two_box_scenes()
    ds = Dataset(make_dataset(root / "analytic", scenes, n_frames=20, width=160, height=120, arc_deg=30))
    models = {vid: {oid: mesh for mesh, oid in objs} for vid, objs in zip(ds.video_ids, scenes)}
    out = root / "results"
    for args in (["--method", "oracle"], ["--method", "one-segment", "--folds", "0"]):
        assert evaluate([*args, "--data", str(ds.root), "--frame-stride", "5", "--out", str(out), "--quiet"]) == 0
    config = load_config(OursConfig, overrides=FAST)
    run_table2(ds, config, out, ("lccp+symseg", "ours-matching"), models=models, progress=False)
    report = root / "report.html"
    write_report(out, report, max_points=MAX_POINTS, models=models)
    pseudo = table2_pipeline(ds, config, out).pseudo_dir()
    return {"dataset": ds, "results": out, "report": report, "html": report.read_text(), "models": models,
            "matches": read_json(pseudo / MATCHES_JSON), "diagnostics": read_json(pseudo / DIAGNOSTICS_JSON)}


def figure(html: str, element_id: str) -> dict:
    m = re.search(f'<script type="application/json" id="{element_id}">(.*?)</script>', html, re.S)
    assert m, element_id
    return json.loads(m.group(1).replace("<\\/", "</"))


def n_points(trace: dict) -> int:
    x = trace["x"]
    return len(base64.b64decode(x["bdata"])) // np.dtype(x["dtype"]).itemsize if isinstance(x, dict) else len(x)


def test_report_holds_every_scene_and_match_offline(run):
    html, ds, matches, diagnostics = run["html"], run["dataset"], run["matches"], run["diagnostics"]
    # every scene: a row and a figure of four panels (RGB, segments + graph, pseudo-labels, ground truth)
    assert re.findall(r'id="fig-scene-([^"]+)"', html) == ds.video_ids
    for vid in ds.video_ids:
        assert f'id="scene-{vid}"' in html
        traces = figure(html, f"fig-scene-{vid}")["data"]
        clouds = [t for t in traces if t["mode"] == "markers" and t["marker"]["size"] == 2]
        assert [t["scene"] for t in clouds] == ["scene", "scene2", "scene3", "scene4"]
        assert len({n_points(t) for t in clouds}) == 1 and 100 < n_points(clouds[0]) <= MAX_POINTS
        n_seg = diagnostics["scenes"][vid]["segments"]
        nodes = [t for t in traces if t["mode"] == "markers" and t["marker"]["size"] == 5]
        assert len(nodes) == 1 and n_points(nodes[0]) == n_seg  # a node per segment, at its centroid
        seg_colours, gt_colours = set(clouds[1]["marker"]["color"]), set(clouds[3]["marker"]["color"])
        assert len(seg_colours - {"#b4b4b4"}) == n_seg  # every segment drawn in a colour of its own
        assert len(gt_colours - {"#b4b4b4"}) >= 1  # ground-truth objects coloured
    # every match: a row with its outcome, and a figure of its two components
    assert matches["matches"] and len(re.findall(r'id="fig-match-', html)) == len(matches["matches"])
    outcomes = Counter()
    for n, m in enumerate(matches["matches"]):
        row = html[html.index(f'<span id="match-{n}">'):]
        row = row[:row.index("</tr>")]
        outcome = match_outcome(len(m["merged_edges"]), [p["reason"] for p in m["pairs"] if not p["accepted"]])
        outcomes[outcome] += 1
        assert f">{outcome}<" in row and f"{m['src_scene']} / {m['src_comp']}" in row
        panels = figure(html, f"fig-match-{n}")["data"]
        assert len(panels) == 4 and n_points(panels[1]) == n_points(panels[3]) == len(m["pairs"])
        assert 0 < n_points(panels[0]) <= MAX_POINTS and 0 < n_points(panels[2]) <= MAX_POINTS
    assert outcomes == diagnostics["pruning"]["matches_by_outcome"]  # the per-match outcomes add up to diagnostics
    # Tables I–III (with the paper's rows), the IoU plot and the montage of every 2-D run
    for title in ("Table I", "Table II", "Table III"):
        assert f"<h2>{title}" in html
    assert "<b>oracle</b>" in html and "<b>one-segment</b>" in html and "paper, real:" in html
    assert len(re.findall(r'<img alt="[^"]+" src="data:image/png;base64,', html)) == 2
    # offline and small: plotly.js once, no resource outside the file
    assert html.count("* plotly.js v") == 1
    markup = re.sub(r"<script\b[^>]*>.*?</script>", "", html, flags=re.S)
    assert re.findall(r'(?:src|href)\s*=\s*"(?!data:|#)', markup) == [] and "<link" not in markup
    assert "@import" not in markup and "url(" not in markup
    assert re.findall(r"<script\b[^>]*\bsrc=", html) == []
    assert run["report"].stat().st_size < SIZE_BOUND


def test_match_figures_are_capped_per_outcome_and_every_match_is_listed(run, tmp_path):
    """--match-figures 1 --match-points 50: one figure per outcome (the first match of each), at most 50 points a
    side, every match still a row (the others marked not drawn), and a line saying how many are drawn."""
    out = tmp_path / "capped.html"
    write_report(run["results"], out, max_points=MAX_POINTS, models=run["models"], match_points=50, match_figures=1)
    html = out.read_text()
    outcomes = [match_outcome(len(m["merged_edges"]), [p["reason"] for p in m["pairs"] if not p["accepted"]])
                for m in run["matches"]["matches"]]
    first = {o: outcomes.index(o) for o in set(outcomes)}
    drawn = sorted(int(n) for n in re.findall(r'id="fig-match-(\d+)"', html))
    assert drawn == sorted(first.values())
    for n in range(len(outcomes)):
        row = html[html.index(f'<span id="match-{n}">'):]
        assert ("(not drawn)" in row[:row.index("</tr>")]) == (n not in drawn)
    for n in drawn:
        panels = figure(html, f"fig-match-{n}")["data"]
        assert 0 < n_points(panels[0]) <= 50 and 0 < n_points(panels[2]) <= 50
    assert len(drawn) < len(outcomes)  # the run has several matches of one outcome: the cap is exercised
    assert f"{len(drawn)} of {len(outcomes)} matches are drawn" in html


def test_bad_input_is_one_line_and_2d_only_results_still_report(run, tmp_path, capsys):
    out = tmp_path / "r.html"
    assert main([str(tmp_path / "nothing"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("inspect: error: ") and str(tmp_path / "nothing") in err and "\n" not in err
    assert main([str(run["results"]), "--out", str(out), "--match-figures", "-1"]) == 2
    assert capsys.readouterr().err.strip() == "inspect: error: --match-figures must be ≥ 0, got -1"
    # the scores without the run's stage files: the missing pseudo stage is named
    scores_only = tmp_path / "scores_only"
    shutil.copytree(run["results"] / SCORES_DIR, scores_only / SCORES_DIR)
    assert main([str(scores_only), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert MATCHES_JSON in err and str(scores_only) in err and "\n" not in err and not out.exists()
    # results of 2-D runs only: no scenes, the tables and plots still
    two_d = tmp_path / "two_d"
    shutil.copytree(run["results"] / SCORES_DIR / "analytic" / "oracle", two_d / SCORES_DIR / "analytic" / "oracle")
    assert main([str(two_d / SCORES_DIR / "analytic"), "--out", str(out)]) == 0
    html = out.read_text()
    assert "No <code>evaluate3d</code> run" in html and "<b>oracle</b>" in html and "fig-scene-" not in html


def test_leaderboard_links_the_report_next_to_it(run, tmp_path):
    build(run["results"], tmp_path)
    assert REPORT_HTML.format(dataset="analytic") not in (tmp_path / "analytic.md").read_text()
    shutil.copy(run["report"], tmp_path / REPORT_HTML.format(dataset="analytic"))
    build(run["results"], tmp_path)
    assert "](analytic_report.html)" in (tmp_path / "analytic.md").read_text()


def browser() -> str:
    for name in ("chromium-headless-shell", "chromium"):
        if shutil.which(name):
            return shutil.which(name)
    pytest.fail("no headless Chromium (Debian: chromium-headless-shell; scripts/install_system_deps.sh installs it)")


@pytest.mark.slow
def test_chromium_draws_the_3d_panels_from_the_file_without_network(run, tmp_path):
    """Headless Chromium in a network namespace of its own (bwrap --unshare-net: loopback only) opens the report
    from its file; WebGL runs on SwiftShader (CPU). The screenshot's scene view has coloured points in each of
    its four panels, not blank canvases."""
    import cv2

    shot = tmp_path / "shot.png"
    argv = ["bwrap", "--dev-bind", "/", "/", "--unshare-net", browser(), "--headless", "--no-sandbox",
            "--enable-unsafe-swiftshader", "--window-size=1600,1000", "--virtual-time-budget=15000",
            f"--screenshot={shot}", run["report"].as_uri()]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=180)
    assert done.returncode == 0 and shot.is_file(), done.stderr[-2000:]
    img = cv2.imread(str(shot))
    assert img.shape[:2] == (1000, 1600)
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    coloured = (hsv[:, :, 1] > 40) & (hsv[:, :, 2] > 40)  # points; the page itself is black, grey and white
    rows = np.nonzero(coloured.sum(1) > 40)[0]  # the scene view: rows crossed by coloured points
    # the same page with WebGL off (--disable-3d-apis) gave 48 such rows (a button, plotly's notice), < 4500 per quarter
    assert len(rows) > 150, len(rows)
    band = coloured[rows]
    quarters = [band[:, i * 400:(i + 1) * 400].sum() for i in range(4)]
    assert min(quarters) > 8000, quarters  # each of the four panels drew points
    assert len(np.unique(img[rows].reshape(-1, 3), axis=0)) > 200  # shaded colours, not flat fills
