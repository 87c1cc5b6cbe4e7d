"""Benchmark: all-pairs scene-graph matching time on synthetic graphs of realistic size.

Synthetic scenes imitate the pipeline's segment graphs: a library of K objects, each a small
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

import argparse
import os
import platform
import resource
import time
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from selfseg.config import to_dict
from selfseg.fileio import write_json
from selfseg.method.matching import MatchConfig, SceneGraph, match_all, match_stats

RESULTS = Path(__file__).parent / "results" / "matching.json"


def make_library(rng: np.random.Generator, n_objects: int = 17, dim: int = 16, n_families: int = 6):
    """Objects as (part features P×dim, part edges) with features clustered by colour family."""
    families = rng.normal(size=(n_families, dim))
    families /= np.linalg.norm(families, axis=1, keepdims=True)
    objects = []
    for _ in range(n_objects):
        n_parts = int(rng.integers(1, 6))
        fam = families[rng.integers(n_families)]
        feats = fam + 0.55 * rng.normal(size=(n_parts, dim)) / np.sqrt(dim)
        feats /= np.linalg.norm(feats, axis=1, keepdims=True)
        edges = [(int(rng.integers(p)), p) for p in range(1, n_parts)]  # random tree
        if n_parts >= 3 and rng.random() < 0.4:  # and sometimes a cycle
            edges.append((0, n_parts - 1))
        objects.append((feats, edges))
    return objects


def make_scene(rng: np.random.Generator, library, scene_id: str, n_in_scene: tuple[int, int] = (4, 17),
               noise: float = 0.06, p_visible: float = 0.9) -> SceneGraph:
    """One synthetic scene graph: a subset of the library in touching clusters."""
    n_obj = int(rng.integers(n_in_scene[0], n_in_scene[1] + 1))
    chosen = rng.choice(len(library), size=min(n_obj, len(library)), replace=False)
    feats, edges, obj_nodes = [], [], []
    for o in chosen:
        f, e = library[o]
        keep = rng.random(len(f)) < p_visible
        keep[rng.integers(len(f))] = True
        idx = np.full(len(f), -1)
        idx[keep] = np.arange(keep.sum()) + len(feats)
        g = f[keep] + noise * rng.normal(size=(int(keep.sum()), f.shape[1]))
        feats += list(g / np.linalg.norm(g, axis=1, keepdims=True))
        nodes = idx[keep]
        edges += [(idx[a], idx[b]) for a, b in e if idx[a] >= 0 and idx[b] >= 0]
        obj_nodes.append(nodes)
    # group objects into clusters (components) of 1–4 touching objects
    order = rng.permutation(len(obj_nodes))
    t = 0
    while t < len(order):
        size = int(rng.integers(1, 5))
        cluster = order[t:t + size]
        for a, b in zip(cluster[:-1], cluster[1:]):
            for _ in range(int(rng.integers(1, 3))):
                edges.append((int(rng.choice(obj_nodes[a])), int(rng.choice(obj_nodes[b]))))
        t += size
    e = np.unique(np.sort(np.array(edges, dtype=np.int64).reshape(-1, 2), axis=1), axis=0)
    n = len(feats)
    _, lab = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)), directed=False)
    comps = [np.nonzero(lab == c)[0] for c in range(lab.max() + 1)]
    return SceneGraph(scene_id, np.array(feats), e, comps)


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
        **match_stats(matches),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[6, 12, 36], help="numbers of scenes")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=RESULTS)
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
    write_json(args.out, {"config": to_dict(cfg), "seed": args.seed, "cpu_count": os.cpu_count(),
                          "load_average_1min": os.getloadavg()[0],
                          "machine": platform.processor() or platform.machine(), "runs": runs})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
