"""Calibration sweeps for the `calibrated` preset, on development seeds only (never seed 0).

    # contact only: physics drops (no rendering), touching GT pairs per scene for each layout
    .venv/bin/python experiments/bench_calibrate.py layout --preset calibrated --seeds 7,11 --scenes 12 \\
        --variant "pile:physics.layout=pile" --variant "spread:physics.layout=spread" [--out experiments/results/calibrate_layout.json]
    # data statistics (evaluate3d --stats) of generated development data under several over-segmentation settings
    .venv/bin/python experiments/bench_calibrate.py stats --data runs/dev7 --data runs/dev11 \\
        --variant "default:" --variant "trunc3:recon.trunc_voxel_multiplier=3" [--config FILE] [--out ...]

A variant is ``NAME:key=value,key=value`` (generation overrides for ``layout``: preset fields with dotted
sub-keys; ``ours`` config overrides for ``stats``). Each prints a table and writes JSON. The statistics
are those of :mod:`selfseg.eval.datastats`; the targets the preset is calibrated to are the paper's
Table II LCCP row: P ≥ .97, R ≤ .85, and a gt-merging ceiling ≥ .93 (over ≥ 12 scenes and 2 seeds).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from common import parse_variant

from selfseg.config import load_config, to_dict
from selfseg.dataset import Dataset
from selfseg.eval.datastats import TOUCH_DIST_M, mesh_distances
from selfseg.eval.provenance import machine
from selfseg.eval.table2 import run_stats
from selfseg.fileio import write_json
from selfseg.generate.presets import preset_config
from selfseg.generate.scene import drop_scene, load_library
from selfseg.method.pipeline import OursConfig
from selfseg.raycast import RaycastScene

TARGETS = {"lccp_P_min": 0.97, "lccp_R_max": 0.85, "gt_merging_IoU_min": 0.93}


def _nested(overrides: list[str]) -> dict:
    """key=value strings (dotted keys, YAML values) → a nested dict of preset overrides."""
    import yaml

    out: dict = {}
    for item in overrides:
        key, _, value = item.partition("=")
        *path, last = key.strip().split(".")
        d = out
        for k in path:
            d = d.setdefault(k, {})
        d[last] = yaml.safe_load(value)
    return out


def layout(args) -> dict:
    """Touching GT pairs, kept objects and pile extent per scene for each variant, physics only."""
    results = {}
    for text in args.variant:
        name, sets = parse_variant(text)
        rows = []
        for seed in args.seeds:
            cfg = preset_config(args.preset, seed=seed, scenes=args.scenes, **_nested(sets))
            library = load_library(cfg)
            for index in range(cfg.scenes):
                t0 = time.perf_counter()
                _, _, chosen, drop, inst = drop_scene(cfg, index, library, Path(args.cache))
                meshes = RaycastScene.from_meshes([library[li].trimesh() for _, li, _ in inst], [T for _, _, T in inst],
                                                  [i for i, _, _ in inst])
                dist = mesh_distances(meshes)
                touching = [(library[inst[i - 1][1]].name, library[inst[j - 1][1]].name)
                            for (i, j), d in dist.items() if d <= TOUCH_DIST_M]
                centres = np.array([T[:2, 3] for _, _, T in inst])
                rows.append({"seed": seed, "scene": index, "kept": len(inst), "dropped": len(chosen),
                             "touching": touching, "extent_m": float(np.linalg.norm(centres - centres.mean(0), axis=1).max()),
                             "seconds": time.perf_counter() - t0})
        t = [len(r["touching"]) for r in rows]
        results[name] = {"overrides": sets, "scenes": rows, "touching_per_scene": float(np.mean(t)),
                         "scenes_without_contact": float(np.mean([x == 0 for x in t])),
                         "kept_per_scene": float(np.mean([r["kept"] for r in rows])),
                         "extent_m": float(np.median([r["extent_m"] for r in rows]))}
        names = sorted({n for r in rows for pair in r["touching"] for n in pair})
        results[name]["touching_objects"] = {n: sum(n in pair for r in rows for pair in r["touching"]) for n in names}
    head = f"{'variant':24s} {'touch/scene':>11s} {'no contact':>10s} {'kept':>5s} {'extent m':>8s}"
    print(head)
    for name, r in results.items():
        print(f"{name:24s} {r['touching_per_scene']:11.2f} {r['scenes_without_contact']:10.2f} "
              f"{r['kept_per_scene']:5.1f} {r['extent_m']:8.3f}")
    return results


def stats(args) -> dict:
    """evaluate3d --stats for every dataset × variant; the overall rows and targets met."""
    results = {}
    for text in args.variant:
        name, sets = parse_variant(text)
        config = load_config(OursConfig, args.config, sets)
        per_data = {}
        for data in args.data:
            ds = Dataset(data)
            t0 = time.perf_counter()
            rec = run_stats(ds, config, Path(args.work))  # one stage cache: variants share what their keys share
            per_data[str(data)] = {"overall": rec["overall"], "seconds": time.perf_counter() - t0,
                                   "content_hash": rec["dataset"]["content_hash"]}
        ov = [d["overall"] for d in per_data.values()]
        n = np.array([o["scenes"] for o in ov], dtype=float)
        mean = lambda f: float(np.sum([f(o) * k for o, k in zip(ov, n)]) / n.sum())  # noqa: E731 (scene-weighted)
        summ = {"scenes": int(n.sum()), "touching_per_scene": mean(lambda o: o["touching_pairs_per_scene"]),
                **{f"{row}_{k}": mean(lambda o, row=row, k=k: o["rows"][row][k])
                   for row in ("lccp", "lccp+symseg", "gt-merging") for k in ("P", "R", "IoU")},
                **{f"lccp_{k}": mean(lambda o, k=k: o["breakdown"]["lccp"][k])
                   for k in ("segments_per_object", "split_share", "no_segment_share", "lost_pruned", "lost_other",
                             "lost_own_parts")},
                "artifact_share": mean(lambda o: o["reconstruction"]["artifact_share"]),
                "coverage": mean(lambda o: o["reconstruction"]["coverage"])}
        summ["targets_met"] = bool(summ["lccp_P"] >= TARGETS["lccp_P_min"] and summ["lccp_R"] <= TARGETS["lccp_R_max"]
                                   and summ["gt-merging_IoU"] >= TARGETS["gt_merging_IoU_min"])
        results[name] = {"overrides": sets, "config": to_dict(config), "per_data": per_data, "summary": summ}
    cols = [("scenes", "d"), ("touching_per_scene", ".2f"), ("lccp_P", ".3f"), ("lccp_R", ".3f"), ("lccp_IoU", ".3f"),
            ("lccp+symseg_P", ".3f"), ("lccp+symseg_R", ".3f"), ("lccp+symseg_IoU", ".3f"), ("gt-merging_IoU", ".3f"),
            ("lccp_segments_per_object", ".2f"), ("lccp_no_segment_share", ".3f"), ("lccp_lost_pruned", ".3f"),
            ("lccp_lost_other", ".3f"), ("lccp_lost_own_parts", ".3f"), ("artifact_share", ".3f"), ("coverage", ".3f"),
            ("targets_met", "")]
    short = {"touching_per_scene": "touch", "lccp_segments_per_object": "segs/obj", "lccp_no_segment_share": "no seg",
             "lccp_lost_pruned": "lost prun", "lccp_lost_other": "lost othr", "lccp_lost_own_parts": "lost own",
             "artifact_share": ">1cm", "targets_met": "targets"}
    label = lambda c: short.get(c, c.replace("lccp+symseg", "sym").replace("gt-merging", "gtmerge"))  # noqa: E731
    print("variant".ljust(28) + " ".join(label(c)[:10].rjust(10) for c, _ in cols))
    for name, r in results.items():
        print(name[:27].ljust(28) + " ".join(format(r["summary"][c], f).rjust(10) for c, f in cols))
    return results


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="mode", required=True)
    a = sub.add_parser("layout")
    a.add_argument("--preset", default="calibrated")
    a.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")], default=[7, 11])
    a.add_argument("--scenes", type=int, default=12)
    a.add_argument("--variant", action="append", required=True)
    a.add_argument("--cache", default="runs/calibrate/physics-cache")
    b = sub.add_parser("stats")
    b.add_argument("--data", action="append", type=Path, required=True)
    b.add_argument("--config", type=Path)
    b.add_argument("--variant", action="append", required=True)
    b.add_argument("--work", default="runs/calibrate/stats")
    for q in (a, b):
        q.add_argument("--out", type=Path)
    args = p.parse_args(argv)
    if args.mode == "layout" and 0 in args.seeds:
        p.error("seed 0 makes the test folds; calibrate on development seeds only")
    results = layout(args) if args.mode == "layout" else stats(args)
    out = args.out or Path(f"experiments/results/calibrate_{args.mode}.json")
    write_json(out, {"mode": args.mode, "argv": sys.argv[1:], "machine": machine(), "targets": TARGETS,
                     "results": results})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
