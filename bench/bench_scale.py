"""Benchmark: local process pools vs Ray, 1 vs 2 workers, and the paper-scale estimate it feeds.

Measures on this machine, for each executor (local, ray) and worker count (1, 2): starting and
stopping the executor; the round trip of one empty task (submit → result, one at a time: a task's
fixed overhead); 200 empty tasks submitted at once (per-task cost when tasks queue); all-pairs
matching of 12 synthetic scenes (bench_matching's generator, ``common.py``) and, with ``--graphs OUT``, of the real
segment graphs and φ1 features an ``evaluate3d --out OUT`` run left (e.g. the benchmark preset's 12
videos); and the tiny preset (Workbench) generated through the ``generate_scenes`` CLI. Matches and
datasets must be identical across every configuration. Then it estimates the paper-scale set (36
videos × 800 frames at 640×480, Cycles) on N nodes from the measured per-frame render cost
(results/generate.json) and per-pair matching cost (results/matching.json).

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_scale.py [--graphs runs/benchmark/results]
    # writes bench/results/scale.json (--out for another file)
"""
from __future__ import annotations

import filecmp
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")  # a private instance on the loopback interface

import numpy as np  # noqa: E402
from common import RESULTS, bench_parser, make_library, make_scene, write_result  # noqa: E402

from selfseg.executor import make_executor  # noqa: E402
from selfseg.fileio import read_json  # noqa: E402
from selfseg.method.matching import MatchConfig, SceneGraph, match_all  # noqa: E402
from selfseg.method.pipeline import FEATURES_NPY, PSEUDO_CACHE_DIR, SEGMENTS_NPZ  # noqa: E402
from selfseg.method.segment_graph import SegmentGraph  # noqa: E402

WORKERS = (1, 2)
PAPER = {"scenes": 36, "frames": 800, "resolution": [640, 480]}


def _noop(x: int) -> int:
    return x


def load_graphs(out: Path) -> list[SceneGraph]:
    """The segment graphs (overseg stage) and φ1 features (pseudo stage) of every video of the ``evaluate3d``
    run in ``out``: the stage folder whose graphs have one row per feature row of each video."""
    pseudo = sorted(out.glob(f"work/ours/*/foldall/{PSEUDO_CACHE_DIR}/all/scenes"))
    if not pseudo:
        raise SystemExit(f"{out}: no evaluate3d pseudo stage (work/ours/*/foldall/{PSEUDO_CACHE_DIR}/all/scenes)")
    feats = {p.stem: np.load(p) for p in sorted((pseudo[0] / FEATURES_NPY.format(video_id="x")).parent.glob("*.npy"))}
    for stages in sorted(out.glob("work/_stages/*")):
        graphs = {v: stages / "overseg" / v / SEGMENTS_NPZ for v in feats}
        if all(p.is_file() for p in graphs.values()):
            loaded = {v: SegmentGraph.load(p) for v, p in graphs.items()}
            if all(len(g.sizes) == len(feats[v]) for v, g in loaded.items()):
                return [SceneGraph(v, feats[v].astype(np.float64), np.asarray(g.edges, np.int64).reshape(-1, 2),
                                   [np.asarray(c, np.int64) for c in g.components()]) for v, g in loaded.items()]
    raise SystemExit(f"{out}: no stage folder under work/_stages holds graphs matching the φ1 features")


def _wall(fn, *args, **kwargs) -> tuple[float, object]:
    t0 = time.perf_counter()
    result = fn(*args, **kwargs)
    return time.perf_counter() - t0, result


def _match_key(matches) -> list:
    return [(m.src_scene, m.src_comp, m.tgt_scene, m.tgt_comp, m.result.node_map, m.result.cost) for m in matches]


def executor_costs(kind: str, workers: int, real: list[SceneGraph] | None) -> dict:
    """Start/stop, one-at-a-time round trip and queued throughput of empty tasks, synthetic 12-scene matching
    and (``real``) matching of real segment graphs, on ``kind`` with ``workers`` workers."""
    t0 = time.perf_counter()
    ex = make_executor(kind, workers=workers)
    ex.submit(_noop, 0).result()  # workers up
    start_s = time.perf_counter() - t0
    for _ in range(5):  # warm every worker
        list(ex.map(_noop, range(workers * 2)))
    t0 = time.perf_counter()
    for i in range(50):
        ex.submit(_noop, i).result()
    round_trip_s = (time.perf_counter() - t0) / 50
    t0 = time.perf_counter()
    assert list(ex.map(_noop, range(200))) == list(range(200))
    queued_s = (time.perf_counter() - t0) / 200
    rng = np.random.default_rng(0)
    library = make_library(rng)
    scenes = [make_scene(rng, library, f"{s:06d}") for s in range(12)]
    match_s, matches = _wall(match_all, scenes, MatchConfig(workers=workers), executor=ex, progress=False)
    out = {"start_s": round(start_s, 3), "task_round_trip_ms": round(1e3 * round_trip_s, 3),
           "task_queued_ms": round(1e3 * queued_s, 3), "matching_12_synthetic_wall_s": round(match_s, 3),
           "matches": _match_key(matches)}
    if real is not None:
        real_s, real_matches = _wall(match_all, real, MatchConfig(workers=workers), executor=ex, progress=False)
        out.update(matching_real_wall_s=round(real_s, 3), real_matches=_match_key(real_matches))
    t0 = time.perf_counter()
    ex.shutdown()
    out["stop_s"] = round(time.perf_counter() - t0, 3)
    return out


def tiny_preset(kind: str, workers: int, out: Path) -> float:
    """Wall seconds of `generate_scenes --preset tiny --renderer workbench` on ``kind`` with ``workers``."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "selfseg.generate.cli", "--preset", "tiny", "--renderer", "workbench",
                    "--out", str(out), "--quiet", "--workers", str(workers), "--executor", kind],
                   check=True, capture_output=True)
    return time.perf_counter() - t0


def _same_tree(a: Path, b: Path) -> bool:
    files = sorted(p.relative_to(a) for p in a.rglob("*"))
    return files == sorted(p.relative_to(b) for p in b.rglob("*")) and all(
        filecmp.cmp(a / p, b / p, shallow=False) for p in files if (a / p).is_file())


def paper_estimate(round_trip_ms: float) -> dict:
    """Wall time of the paper-scale set on N nodes of C cores from measured costs: one Ray task per scene,
    each reserving a node's C cores (Cycles renders with all of them), so ceil(36 / N) rounds of one scene's
    CPU seconds / C; all-pairs matching's CPU seconds spread over N·C cores. Assumes Cycles scales linearly
    with cores (not measured here) and a shared filesystem that keeps up."""
    gen = read_json(RESULTS / "generate.json")
    frame = next(r for r in gen["per_frame"] if r["device"] == "cycles-cpu" and r["resolution"] == [640, 480])
    match = read_json(RESULTS / "matching.json")
    pair_cpu_s = max(r["cpu_s_per_scene_pair"] for r in match["runs"])
    scene_cpu_s = PAPER["frames"] * frame["frame_cpu_s"] + frame["setup_s"]
    pairs = PAPER["scenes"] * (PAPER["scenes"] - 1) // 2
    rows = []
    for cores in (2, 16):
        for nodes in (1, 2, 4, 9, 18, 36):
            render_s = math.ceil(PAPER["scenes"] / nodes) * scene_cpu_s / cores
            match_s = pairs * pair_cpu_s / (nodes * cores)
            rows.append({"nodes": nodes, "cores_per_node": cores, "render_h": round(render_s / 3600, 2),
                         "matching_s": round(match_s, 1), "total_h": round((render_s + match_s) / 3600, 2)})
    return {"basis": {"cycles_cpu_s_per_frame_640x480": frame["frame_cpu_s"], "scene_cpu_s": round(scene_cpu_s),
                      "matching_cpu_s_per_scene_pair": round(pair_cpu_s, 4), "scene_pairs": pairs},
            "ray_overhead_fraction_of_one_scene": round(round_trip_ms / 1e3 / (scene_cpu_s / 2), 9),
            "rows": rows}


def main() -> None:
    p = bench_parser(__doc__, "scale.json")
    p.add_argument("--graphs", type=Path, help="an evaluate3d --out folder: also match its real segment graphs")
    args = p.parse_args()
    real = load_graphs(args.graphs) if args.graphs else None
    configs = [(kind, w) for kind in ("local", "ray") for w in WORKERS]
    costs = {f"{kind}-{w}": executor_costs(kind, w, real) for kind, w in configs}
    first = next(iter(costs.values()))
    for key in ("matches", "real_matches"):
        if key in first:
            assert all(c[key] == first[key] for c in costs.values()), f"{key} differ between executors"
    n_real = sum(bool(m[4]) for m in first.get("real_matches", []))
    for c in costs.values():
        c.pop("matches"), c.pop("real_matches", None)
    with tempfile.TemporaryDirectory() as tmp:
        for kind, w in configs:
            costs[f"{kind}-{w}"]["tiny_preset_workbench_wall_s"] = round(tiny_preset(kind, w, Path(tmp) / f"{kind}-{w}"), 2)
        identical = all(_same_tree(Path(tmp) / "local-1", Path(tmp) / f"{kind}-{w}") for kind, w in configs)
    assert identical, "the tiny preset differs between executors"
    result = {"workers": list(WORKERS), "costs": costs, "tiny_identical": identical,
              "real_graphs": None if real is None else {"from": str(args.graphs), "scenes": len(real),
                                                        "segments": int(sum(len(g.features) for g in real)),
                                                        "nonempty_matches": n_real},
              "paper_estimate": paper_estimate(costs["ray-2"]["task_round_trip_ms"])}
    write_result(args.out, result)
    keys = ["start_s", "stop_s", "task_round_trip_ms", "task_queued_ms", "matching_12_synthetic_wall_s",
            *(["matching_real_wall_s"] if real is not None else []), "tiny_preset_workbench_wall_s"]
    print(f"{'':30}" + "".join(f"{k:>10}" for k in costs))
    for key in keys:
        print(f"{key:30}" + "".join(f"{c[key]:>10}" for c in costs.values()))
    if real is not None:
        print(f"real graphs: {len(real)} scenes from {args.graphs}, {n_real} non-empty matches (equal everywhere)")
    print(f"tiny preset byte-identical across executors and worker counts: {identical}")
    est = result["paper_estimate"]
    print(f"Ray round trip / one paper scene's render on 2 cores: {est['ray_overhead_fraction_of_one_scene']:.2e}")
    for r in est["rows"]:
        print(f"  {r['nodes']:>2} nodes × {r['cores_per_node']:>2} cores: render {r['render_h']:>7} h, "
              f"matching {r['matching_s']:>7} s, total {r['total_h']} h")


if __name__ == "__main__":
    main()
