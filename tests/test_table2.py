"""Table II (``evaluate3d``): the pipeline's 3-D segmentations scored against GT points on ray-cast scenes."""
import json
import shutil

import numpy as np
import pytest

from selfseg.analytic import make_dataset, two_box_scenes
from selfseg.config import load_config
from selfseg.dataset import Dataset
from selfseg.eval.cli import evaluate3d_main as main
from selfseg.eval.layout import FAILED_JSON, FRAMES_JSONL, SCORES_JSON, STAGES_DIR, WORK_DIR
from selfseg.eval.leaderboard import main as build_leaderboards
from selfseg.eval.points import evaluate_points
from selfseg.eval.table2 import FOLD, ROWS, alignment, format_matching, run_table2, segment_scenes
from selfseg.fileio import read_json
from selfseg.method.pipeline import MATCH_CACHE_DIR, OursConfig
from test_pipeline import FAST


def test_cli_missing_dataset(tmp_path, capsys):
    missing = tmp_path / "nope"
    assert main(["--data", str(missing), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "evaluate3d: error:" in err and str(missing) in err
    assert not (tmp_path / "out").exists()


def _two_box_dataset(root) -> tuple[Dataset, dict]:
    """Ray-cast two-box scenes (20 frames over 30°) and their GT models per video."""
    scenes = two_box_scenes()
    ds = Dataset(make_dataset(root, scenes, n_frames=20, width=160, height=120, arc_deg=30))
    # analytic models are placed in the world (T_cam_model = T_cam_world): one model set per video
    return ds, {vid: {oid: mesh for mesh, oid in objs} for vid, objs in zip(ds.video_ids, scenes)}


def test_cli_bad_executor_one_line(analytic_dataset, tmp_path, capsys):
    assert main(["--data", str(analytic_dataset), "--out", str(tmp_path), "--executor", "dask"]) == 2
    assert capsys.readouterr().err.strip() == "evaluate3d: error: --executor must be one of local, ray, got 'dask'"


@pytest.mark.slow
def test_matching_on_ray_equals_local(tmp_path):
    """evaluate3d --executor ray: the matching and registration tasks on Ray give the local pool's result."""
    from selfseg.executor import make_executor

    ds, models = _two_box_dataset(tmp_path / "analytic")
    cfg = load_config(OursConfig, overrides=FAST)
    out = tmp_path / "results"
    local = run_table2(ds, cfg, out, ("ours-matching",), models=models, progress=False)[0]
    pseudo = out / WORK_DIR.format(name="ours", dataset=ds.name, fold=FOLD) / "pseudo"
    matches_local = read_json(next(pseudo.rglob("matches.json")))
    shutil.rmtree(pseudo)  # φ1 and the per-video stages stay cached: only matching and pruning run again
    (out / SCORES_JSON.format(dataset=ds.name, name="ours-matching", fold=FOLD)).unlink()  # or the row is kept
    for kept in (out / STAGES_DIR).glob(f"*/{MATCH_CACHE_DIR}"):
        shutil.rmtree(kept)  # the matching too, or it would be read back
    tasks = []
    with make_executor("ray", workers=2) as ex:
        submit = ex.submit
        ex.submit = lambda fn, *a, **k: (tasks.append(fn.__name__), submit(fn, *a, **k))[1]  # count the Ray tasks
        on_ray = run_table2(ds, cfg, out, ("ours-matching",), models=models, progress=False, executor=ex)[0]
    assert tasks  # matching (and registration) ran as Ray tasks
    matches_ray = read_json(next(pseudo.rglob("matches.json")))
    timing = ("solver_s", "cpu_s")
    stats = [{k: v for k, v in m["match_stats"].items() if k not in timing} for m in (matches_local, matches_ray)]
    assert stats[0] == stats[1] and matches_local["n_decisions"] > 0
    assert [m["node_map"] for m in matches_local["matches"]] == [m["node_map"] for m in matches_ray["matches"]]
    assert matches_local["merged_groups"] == matches_ray["merged_groups"]
    assert on_ray["metrics"] == local["metrics"]


@pytest.mark.slow
def test_table2_rows_alignment_and_leaderboard(tmp_path):
    ds, models = _two_box_dataset(tmp_path / "analytic")
    cfg = load_config(OursConfig, overrides=FAST)
    out = tmp_path / "results"
    records = run_table2(ds, cfg, out, ROWS, models=models, progress=False)

    assert [r["name"] for r in records] == list(ROWS)
    for r in records:
        saved = read_json(out / SCORES_JSON.format(dataset=ds.name, name=r["name"], fold=FOLD))
        assert saved["task"] == "3d" and saved["fold"] == FOLD and sorted(saved["per_video"]) == ds.video_ids
        assert saved["metrics"]["n_frames"] == len(ds.video_ids)  # one "frame" (point cloud) per video
        sidecar = (out / FRAMES_JSONL.format(dataset=ds.name, name=r["name"], fold=FOLD)).read_text().splitlines()
        assert [json.loads(line)["video_id"] for line in sidecar] == ds.video_ids
        assert r["scored_fraction_min"] > 0.8  # aligned: most reconstructed points lie on a GT object
    lccp, symseg, matching, gt_merging = (r["metrics"] for r in records)
    assert records[0]["config"]["overseg"]["use_symseg"] is False
    assert lccp["IoU"] > 0.8 and lccp["P"] > 0.9  # boxes and a cylinder: convex, so LCCP finds them
    assert symseg["IoU"] > 0.8 and matching["IoU"] > 0.8
    assert gt_merging["IoU"] >= symseg["IoU"] - 1e-9  # merging same-instance neighbours can only help here
    assert records[0]["pose_drift"]["drift_pos_mean_m"] < 0.02  # 20 frames over 30°: little drift
    # the matching record: the pseudo stage's diagnostics plus its ground-truth scores
    assert all("matching" not in r for i, r in enumerate(records) if i != 2)
    m = records[2]["matching"]
    assert sorted(m["scenes"]) == ds.video_ids and m["totals"]["segments"] == sum(
        s["segments"] for s in m["scenes"].values())
    c = m["gt"]["cosine"]
    # objects 1, 2, 3 reappear (1 in three scenes, 2 and 3 in two): at least 3 + 1 + 1 same-object pairs
    assert c["same_object"]["n"] >= 5 and c["different_object"]["n"] > 0
    for part in ("within", "across"):
        p = m["gt"][part]["precision"]
        assert p is None or 0.0 <= p <= 1.0
    assert "merges within scenes" in format_matching(m)

    # the alignment matters: scoring the first-camera-frame cloud as if it were the dataset's frame fails
    scenes_seg = segment_scenes(ds, cfg, out, ("lccp+symseg",)).scenes  # cached: reloads labels
    for s in scenes_seg:
        T, drift = alignment(s.recon, ds.labeled(s.video_id))
        assert drift["drift_pos_mean_m"] < 0.03  # camera positions; the cloud itself is anchored at f0
        good = evaluate_points(s.recon.points_w, s.labels["lccp+symseg"] + 1, ds, s.video_id, T,
                               models=models[s.video_id])
        wrong = evaluate_points(s.recon.points_w, s.labels["lccp+symseg"] + 1, ds, s.video_id, np.eye(4),
                                models=models[s.video_id])
        assert good["IoU"] == pytest.approx(records[1]["per_video"][s.video_id]["IoU"])
        n = len(s.recon.points_w)
        assert good["n_points_scored"] > 0.8 * n and wrong["n_points_scored"] < 0.1 * n
        assert np.nan_to_num(wrong["IoU"]) < good["IoU"] - 0.5  # NaN: no point lies on a GT object

    lb = tmp_path / "lb"
    assert build_leaderboards(["--results", str(out), "--out", str(lb)]) == 0
    md = (lb / f"{ds.name}.md").read_text()
    table2 = md[md.index("## Table II"):md.index("## Table III")]
    for row in ROWS:
        assert f"**{row}**" in table2

    # the same run again (a resumed one) keeps every row's record as it is, without scoring it again; another
    # max_dist_m scores again
    files = sorted(out.glob(SCORES_JSON.format(dataset=ds.name, name="*", fold=FOLD)))
    stamps = [p.stat().st_mtime_ns for p in files]
    assert run_table2(ds, cfg, out, ROWS, models=models, progress=False) == records
    assert [p.stat().st_mtime_ns for p in files] == stamps and len(files) == len(ROWS)
    farther = run_table2(ds, cfg, out, ("lccp",), models=models, progress=False, max_dist_m=0.02)[0]
    lccp_path = out / SCORES_JSON.format(dataset=ds.name, name="lccp", fold=FOLD)
    assert farther["options"]["max_dist_m"] == 0.02 and lccp_path.stat().st_mtime_ns != stamps[files.index(lccp_path)]

    # matching over its CPU budget: the ours-matching row's outcome is a failure record (its earlier scores go), the
    # other rows are scored as before; run again, the failure is kept (the same run would pass the same budget)
    over = load_config(OursConfig, overrides=[*FAST, "pseudo.match.cpu_budget_per_pair_s=1e-9"])
    again = run_table2(ds, over, out, ROWS, models=models, progress=False)
    assert [r["name"] for r in again] == list(ROWS) and "CPU budget" in again[2]["failure"]["message"]
    assert [r["metrics"] for i, r in enumerate(again) if i != 2] == [r["metrics"] for i, r in enumerate(records) if i != 2]
    assert read_json(out / FAILED_JSON.format(dataset=ds.name, name="ours-matching", fold=FOLD))["task"] == "3d"
    assert not (out / SCORES_JSON.format(dataset=ds.name, name="ours-matching", fold=FOLD)).exists()
    assert run_table2(ds, over, out, ("ours-matching",), models=models, progress=False) == [again[2]]
