"""What the experiment scripts share; no script imports another.

* config variants (``bench_supervised_levers.py``, ``bench_matching_levers.py``, ``bench_calibrate.py``): parsing a
  variant, running one variant's command, and keeping earlier rows in the JSON;
* the runs' fold folders (``bench_fold_merges.py``, ``bench_isolation.py``, ``bench_registration_oracle.py``):
  the arguments, each fold's pseudo-label stage, ``evaluate3d``'s segments with their ground-truth labels, and
  writing the rows with the dataset and config they were measured on.

Every script writes its JSON to ``experiments/results/`` unless told otherwise; the dated pages of
``docs/experiments/`` cite them.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from selfseg.config import load_config
from selfseg.dataset import Dataset
from selfseg.eval.layout import results_key
from selfseg.eval.points import GT_MAX_DIST_M
from selfseg.eval.table2 import labeled_scenes
from selfseg.fileio import read_json, write_json
from selfseg.method.pipeline import PSEUDO_CACHE_DIR, PSEUDO_STAGE, OursConfig
from selfseg.method.pruning import PruneConfig
from selfseg.method.pseudolabels import SceneData, segment_clouds
from selfseg.stages import StageCache


def parse_variant(text: str) -> tuple[str, list[str]]:
    """"NAME:a=1,b.c=[2,3]" → ("NAME", ["a=1", "b.c=[2,3]"]): commas inside brackets stay in their value."""
    name, _, rest = text.partition(":")
    if not name or any(c in name for c in "/@ "):
        raise ValueError(f"variant {text!r}: needs a NAME (no '/', '@' or space) before ':'")
    items, depth, cur = [], 0, ""
    for c in rest:
        depth += (c in "[{") - (c in "]}")
        if c == "," and depth == 0:
            items.append(cur)
            cur = ""
        else:
            cur += c
    items.append(cur)
    sets = [s.strip() for s in items if s.strip()]
    bad = [s for s in sets if "=" not in s]
    if bad:
        raise ValueError(f"variant {text!r}: {bad} are not key=value")
    return name, sets


def run_variant_command(bench: str, name: str, cmd: list[str], config: str, sets: list[str]) -> float:
    """Run ``cmd`` with ``--config config`` (if given) and a ``--set`` per item of ``sets``, printed first;
    returns its wall time (s). A failed command ends the bench with one line."""
    cmd = [*cmd, *(["--config", config] if config else []), *[a for s in sets for a in ("--set", s)]]
    print(f"[{name}] {' '.join(cmd)}", flush=True)
    t0 = time.perf_counter()
    rc = subprocess.call(cmd)
    if rc != 0:
        raise SystemExit(f"{bench}: variant {name}: {Path(cmd[0]).name} exited with {rc}")
    return time.perf_counter() - t0


def save_rows(path: str | Path, rows: list[dict], ident: Callable[[dict], tuple], what: str) -> None:
    """Write ``rows`` to the JSON at ``path`` after the rows it already holds, minus those with the same ``ident``."""
    path = Path(path)
    old = read_json(path)["rows"] if path.is_file() else []
    new_ids = {ident(r) for r in rows}
    write_json(path, {"what": what, "rows": [r for r in old if ident(r) not in new_ids] + rows})


def parse_inputs(bench: str, variants: list[str], data: str) -> list[tuple[str, list[str]]] | None:
    """The parsed ``--variant`` texts, or None after one line on stderr when one is malformed or ``data`` is
    not a dataset folder (the bench then exits 2)."""
    if not (Path(data) / "dataset_info.json").is_file():
        print(f"{bench}: {data}: not a dataset (no dataset_info.json)", file=sys.stderr)
        return None
    try:
        return [parse_variant(v) for v in variants]
    except ValueError as e:
        print(f"{bench}: {e}", file=sys.stderr)
        return None


def pseudo_stage(fold_dir: Path) -> Path:
    """A fold's pseudo-label stage folder, where :meth:`Ours.pseudo_labels` wrote it."""
    return StageCache(fold_dir / PSEUDO_CACHE_DIR).path(*PSEUDO_STAGE)


def gt_labeled(dataset: Dataset, config: OursConfig, results: str):
    """(segmentations, alignments, GT instance per point) of every video from ``evaluate3d``'s stages in RESULTS."""
    return labeled_scenes(dataset, config, Path(results), ("lccp+symseg",), None, GT_MAX_DIST_M, None, gt_labels=True)


def segment_clouds_of(scene, prune: PruneConfig) -> list[np.ndarray]:
    """Each segment's points of an ``evaluate3d`` scene, subsampled as pruning subsamples them."""
    n = scene.graph.n_segments
    return segment_clouds(SceneData(scene.video_id, scene.recon.points_w, scene.graph, np.zeros((n, 1))),
                          prune.max_points_per_node, prune.seed)


def fold_dirs(bench: str, results: str, dataset: Dataset, run: str, folds: str = "") -> list[Path] | None:
    """The fold work folders of ``run`` (only the comma-separated fold numbers ``folds``, if given); None after
    one line on stderr when there are none."""
    dirs = sorted(Path(results, "work", run, results_key(Path(results), dataset)).glob("fold[0-9]*"))
    if folds:
        dirs = [d for d in dirs if d.name[4:] in folds.split(",")]
    if not dirs:
        print(f"{bench}: {results}: no folds of run {run!r}", file=sys.stderr)
    return dirs or None


def fold_bench_parser(doc: str, json_default: str) -> argparse.ArgumentParser:
    """The arguments of the benches that read runs' fold folders: --data, --config, --results, --run (repeated),
    --folds and --json."""
    p = argparse.ArgumentParser(description=doc.split("\n")[0])
    p.add_argument("--data", required=True, help="a development dataset (reads its ground truth)")
    p.add_argument("--config", required=True, help="the config the runs and evaluate3d used")
    p.add_argument("--results", required=True, help="the runs' results folder (evaluate --out), with evaluate3d's")
    p.add_argument("--run", action="append", required=True, help="a run name (its folds' work folders)")
    p.add_argument("--folds", default="", help="fold numbers, comma-separated (default: every fold folder)")
    p.add_argument("--json", default=json_default)
    return p


def runs_folds(bench: str, args: argparse.Namespace, dataset: Dataset) -> list[tuple[str, Path]] | None:
    """(run, fold folder) for every ``--run`` and fold; None after one line on stderr when a run has none."""
    out = []
    for run in args.run:
        folds = fold_dirs(bench, args.results, dataset, run, args.folds)
        if folds is None:
            return None
        out += [(run, f) for f in folds]
    return out


def fold_bench_inputs(bench: str, args: argparse.Namespace):
    """What the fold benches start from: (dataset, config, segmentations, alignments, GT instance per point,
    [(run, fold folder)]), or None after one line on stderr when a run has no folds."""
    dataset = Dataset(args.data)
    folds = runs_folds(bench, args, dataset)
    if folds is None:
        return None
    config = load_config(OursConfig, args.config)
    seg, aligned, gt_inst = gt_labeled(dataset, config, args.results)
    return dataset, config, seg, aligned, gt_inst, folds


def phi1_features(bench: str, features: str, scenes) -> dict[str, np.ndarray] | None:
    """φ1's feature per segment of each of ``scenes`` (segmentations with ``video_id`` and ``graph``) that has a
    ``<video>.npy`` in the folder ``features`` (one fold's training videos); None, after one line on stderr, when
    the folder has none or a file's rows do not match its video's segments (another over-segmentation's φ1)."""
    out = {}
    for s in scenes:
        f = Path(features) / f"{s.video_id}.npy"
        if f.is_file():
            out[s.video_id] = np.load(f)
            if len(out[s.video_id]) != s.graph.n_segments:
                print(f"{bench}: {f}: {len(out[s.video_id])} features for {s.graph.n_segments} segments (another "
                      "over-segmentation's φ1?)", file=sys.stderr)
                return None
    if not out:
        print(f"{bench}: {features}: no <video>.npy feature file of this dataset's videos", file=sys.stderr)
        return None
    return out


def save(path: str, what: str, data: str, dataset: Dataset, config: str, rows: list[dict]) -> None:
    """Write the bench's rows with the dataset and config they were measured on."""
    write_json(path, {"what": what, "data": str(Path(data).resolve()), "dataset_hash": dataset.content_hash(),
                      "config": config, "rows": rows})
    print(f"wrote {path}")


def touching_pairs(gt: np.ndarray, min_contact_px: int) -> list[tuple[int, int]]:
    """Pairs (a < b) of GT instances of ``gt`` (H×W, 0 = background) with ≥ ``min_contact_px`` pixels of one
    within 2 px (8-connected dilation by 2) of the other."""
    kernel = np.ones((5, 5), np.uint8)
    ids = [int(i) for i in np.unique(gt) if i]
    grown = {i: cv2.dilate((gt == i).astype(np.uint8), kernel).astype(bool) for i in ids}
    return [(a, b) for k, a in enumerate(ids) for b in ids[k + 1:] if np.count_nonzero(grown[a] & (gt == b)) >= min_contact_px]


def joined(pred: np.ndarray, gt: np.ndarray, a: int, b: int) -> bool:
    """One predicted segment (≠ 0) holds at least half of instance ``a``'s and half of ``b``'s pixels."""
    for s in np.unique(pred[(gt == a) | (gt == b)]):
        if s and min(np.mean(pred[gt == a] == s), np.mean(pred[gt == b] == s)) >= 0.5:
            return True
    return False
