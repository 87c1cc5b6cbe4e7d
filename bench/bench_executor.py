"""Benchmark: what Ray costs over local process pools, and the paper-scale estimate it feeds.

Measures on this machine, with 2 workers each: starting and stopping the executor; the round trip
of one empty task (submit → result, one at a time: a task's fixed overhead); 200 empty tasks
submitted at once (per-task cost when tasks queue); all-pairs matching of 12 synthetic scenes
(bench_matching's generator; results must be equal); and the tiny preset (Workbench) generated
through the ``generate_scenes`` CLI (the datasets must be byte-identical). Then it estimates the
paper-scale set (36 videos × 800 frames at 640×480, Cycles) on N nodes from the measured per-frame
render cost (results/generate.json) and per-pair matching cost (results/matching.json).

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_executor.py   # writes bench/results/executor.json
"""
from __future__ import annotations

import filecmp
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")  # a private instance on the loopback interface

import numpy as np  # noqa: E402

from bench_matching import make_library, make_scene  # noqa: E402
from selfseg.executor import make_executor  # noqa: E402
from selfseg.fileio import read_json, write_json  # noqa: E402
from selfseg.method.matching import MatchConfig, match_all  # noqa: E402

RESULTS = Path(__file__).parent / "results"
WORKERS = 2
PAPER = {"scenes": 36, "frames": 800, "resolution": [640, 480]}


def _noop(x: int) -> int:
    return x


def executor_costs(kind: str) -> dict:
    """Start/stop, one-at-a-time round trip and queued throughput of empty tasks, and 12-scene matching."""
    t0 = time.perf_counter()
    ex = make_executor(kind, workers=WORKERS)
    ex.submit(_noop, 0).result()  # workers up
    start_s = time.perf_counter() - t0
    for _ in range(5):  # warm every worker
        list(ex.map(_noop, range(WORKERS * 2)))
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
    t0 = time.perf_counter()
    matches = match_all(scenes, MatchConfig(), executor=ex, progress=False)
    match_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    ex.shutdown()
    stop_s = time.perf_counter() - t0
    return {"start_s": round(start_s, 3), "stop_s": round(stop_s, 3), "task_round_trip_ms": round(1e3 * round_trip_s, 3),
            "task_queued_ms": round(1e3 * queued_s, 3), "matching_12_scenes_wall_s": round(match_s, 3),
            "matches": [(m.src_scene, m.src_comp, m.tgt_scene, m.tgt_comp, m.result.node_map, m.result.cost)
                        for m in matches]}


def tiny_preset(kind: str, out: Path) -> float:
    """Wall seconds of `generate_scenes --preset tiny --renderer workbench` on ``kind`` with 2 workers."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "selfseg.generate.cli", "--preset", "tiny", "--renderer", "workbench",
                    "--out", str(out), "--quiet", "--workers", str(WORKERS), "--executor", kind],
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
    local, ray = executor_costs("local"), executor_costs("ray")
    assert local.pop("matches") == ray.pop("matches"), "matching differs between local and ray"
    with tempfile.TemporaryDirectory() as tmp:
        tiny = {k: round(tiny_preset(k, Path(tmp) / k), 2) for k in ("local", "ray")}
        identical = _same_tree(Path(tmp) / "local", Path(tmp) / "ray")
    assert identical, "tiny preset differs between local and ray"
    result = {"machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "loadavg": os.getloadavg()},
              "workers": WORKERS, "local": local, "ray": ray,
              "tiny_preset_workbench_wall_s": tiny, "tiny_identical": identical,
              "paper_estimate": paper_estimate(ray["task_round_trip_ms"])}
    write_json(RESULTS / "executor.json", result)
    print(f"{'':24}{'local':>10}{'ray':>10}")
    for key in ("start_s", "stop_s", "task_round_trip_ms", "task_queued_ms", "matching_12_scenes_wall_s"):
        print(f"{key:24}{local[key]:>10}{ray[key]:>10}")
    print(f"{'tiny_preset_wall_s':24}{tiny['local']:>10}{tiny['ray']:>10}   (byte-identical: {identical})")
    est = result["paper_estimate"]
    print(f"Ray round trip / one paper scene's render on 2 cores: {est['ray_overhead_fraction_of_one_scene']:.2e}")
    for r in est["rows"]:
        print(f"  {r['nodes']:>2} nodes × {r['cores_per_node']:>2} cores: render {r['render_h']:>7} h, "
              f"matching {r['matching_s']:>7} s, total {r['total_h']} h")


if __name__ == "__main__":
    main()
