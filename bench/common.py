"""What the speed benchmarks share (no bench imports another): the arguments, the machine record and writing the
JSON, and the synthetic segment graphs of ``bench_matching.py`` and ``bench_scale.py``.

Each bench writes ``bench/results/<name>.json`` (``--out`` for another file): its measurements, the machine it ran
on (:func:`selfseg.eval.provenance.machine`: CPU, logical CPUs, load average, Python, platform), the commit and
the package versions.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from selfseg.eval.provenance import git_info, machine, package_versions
from selfseg.fileio import write_json
from selfseg.method.matching import SceneGraph

RESULTS = Path(__file__).resolve().parent / "results"  # the benches' JSON


def bench_parser(doc: str, out: str) -> argparse.ArgumentParser:
    """A bench's arguments: the first line of its docstring ``doc`` as the description, and ``--out`` (default
    ``bench/results/<out>``)."""
    p = argparse.ArgumentParser(description=doc.split("\n")[0])
    p.add_argument("--out", type=Path, default=RESULTS / out, help=f"the JSON to write (default bench/results/{out})")
    return p


def write_result(path: str | os.PathLike, result: dict, load_at_start: tuple[float, ...] | None = None) -> None:
    """Write a bench's ``result`` to ``path`` with the machine record (the load average when it started too, if
    given: the cores may be shared), the commit and the package versions; print where."""
    record = machine()
    if load_at_start is not None:
        record["load_average_start"] = [round(x, 2) for x in load_at_start]
    write_json(path, {**result, "machine": record, "git": git_info(), "versions": package_versions()})
    print(f"wrote {path}")


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
