"""Benchmark: all-pairs scene-graph matching time on synthetic graphs of realistic size.

Synthetic scenes (``common.py``) imitate the pipeline's segment graphs: a library of K objects, each a small
graph of 1–5 parts (segments) with a 16-D unit feature per part; parts of different objects in
the same "colour family" have similar features (cosine ≈ 0.8), so there are near-confusions.
A scene holds a random subset of the objects; each part is observed with probability
``p_visible`` and with feature noise; objects are grouped into touching clusters (weakly
connected components) joined by one or two contact edges. Scenes have 10–60 nodes.

Usage::

    .venv/bin/python bench/bench_matching.py              # N = 6, 12, 36, writes bench/results/matching.json
    .venv/bin/python bench/bench_matching.py --n 6 --workers 1
"""
from __future__ import annotations

import resource
import time

import numpy as np
from common import bench_parser, make_library, make_scene, write_result

from selfseg.config import to_dict
from selfseg.method.matching import MatchConfig, match_all, match_stats


def _cpu_s() -> float:
    """User + system CPU seconds of this process and its reaped children."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def run(n_scenes: int, cfg: MatchConfig, seed: int = 0) -> dict:
    """Match all pairs of ``n_scenes`` synthetic scenes and return timing and solver statistics."""
    rng = np.random.default_rng(seed)
    library = make_library(rng)
    scenes = [make_scene(rng, library, f"{s:06d}") for s in range(n_scenes)]
    sizes = [len(g.features) for g in scenes]
    start, cpu0 = time.perf_counter(), _cpu_s()
    matches = match_all(scenes, cfg)  # a ProcessPool's workers are reaped before it returns
    wall, cpu = time.perf_counter() - start, _cpu_s() - cpu0
    n_pairs = n_scenes * (n_scenes - 1) // 2
    solve = np.array([m.result.solve_s for m in matches if m.result.status != "prefiltered_empty"])
    return {
        "n_scenes": n_scenes,
        "scene_pairs": n_pairs,
        "nodes_per_scene": {"min": min(sizes), "mean": float(np.mean(sizes)), "max": max(sizes)},
        "components_per_scene": float(np.mean([len(g.components) for g in scenes])),
        "wall_s": wall,
        "wall_s_per_scene_pair": wall / n_pairs,
        "cpu_s": cpu,
        "cpu_s_per_scene_pair": cpu / n_pairs,
        "solve_s_per_solved_pair": {"mean": float(solve.mean()) if len(solve) else 0.0,
                                    "max": float(solve.max()) if len(solve) else 0.0},
        **match_stats(matches, cfg),
    }


def main() -> None:
    ap = bench_parser(__doc__, "matching.json")
    ap.add_argument("--n", type=int, nargs="+", default=[6, 12, 36], help="numbers of scenes")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    cfg = MatchConfig(workers=args.workers)
    runs = []
    for n in args.n:
        r = run(n, cfg, args.seed)
        print(f"N={n:3d}: {r['wall_s']:.1f} s total, {r['wall_s_per_scene_pair']*1000:.1f} ms per scene pair "
              f"(CPU {r['cpu_s_per_scene_pair']*1000:.1f} ms), "
              f"prefilter {r['prefilter_rate']:.1%}, LP integral {r['lp_integral_rate']:.1%} of "
              f"{r['solved']} solved, time-limit hits {r['time_limit_hits']}")
        runs.append(r)
    write_result(args.out, {"config": to_dict(cfg), "seed": args.seed, "runs": runs})


if __name__ == "__main__":
    main()
