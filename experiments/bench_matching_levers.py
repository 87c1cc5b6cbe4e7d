"""Diagnostic, not a test: what graph matching finds with φ1 trained under named config variants.

    .venv/bin/python experiments/bench_matching_levers.py --data DIR --config configs/ours-calibrated.yaml
        --variant NAME:key=value,key=value ... [--set KEY=VALUE ...] [--out runs/matching-levers]
        [--json experiments/results/matching_levers.json]

Each variant runs ``evaluate3d --data DIR --config CONFIG --set stage_dir=OUT/_stages --set ... --rows
lccp+symseg,ours-matching --out OUT/NAME`` (the real CLI, in its own process; the variants share the
reconstruction and over-segmentation stages, and a φ1 trained with the same settings), then reads its
records back: Table II's LCCP + SymSeg and after-matching rows, how many component pairs the pre-filter
dropped, the merges with their ground-truth precision and recall, and φ1's cosine between segments of the
same object and of different objects in different scenes. Variants are given as in
``experiments/common.py`` (``NAME:a=1,b.c=[2,3]``). Run it on a development dataset, never on the
seed-0 test data. The JSON keeps the rows of earlier calls (keyed by dataset and variant) and replaces
those run again.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from common import parse_inputs, run_variant_command, save_rows

from selfseg.dataset import Dataset
from selfseg.eval.layout import SCORES_JSON, results_key
from selfseg.fileio import read_json

ROWS = ("lccp+symseg", "ours-matching")


def run_variant(args, name: str, sets: list[str]) -> dict:
    """Run ``evaluate3d`` for one variant and read its records back."""
    out = Path(args.out) / name
    cmd = [str(Path(sys.executable).with_name("evaluate3d")), "--data", args.data, "--rows", ",".join(ROWS),
           "--out", str(out), "--quiet", "--set", f"stage_dir={Path(args.out).resolve() / '_stages'}"]
    wall_s = run_variant_command("bench_matching_levers", name, cmd, args.config, [*args.overrides, *sets])
    ds = Dataset(args.data)
    key = results_key(out, ds)
    rec = {r: read_json(out / SCORES_JSON.format(dataset=key, name=r, fold="all")) for r in ROWS}
    m = rec["ours-matching"]["matching"]
    cos = m["gt"]["cosine"]
    row = {"variant": name, "data": str(Path(args.data).resolve()), "dataset_hash": ds.content_hash(),
           "config": args.config, "sets": [*args.overrides, *sets], "wall_s": round(wall_s, 1),
           "commit": rec["ours-matching"]["git"]["commit"],
           "table2": {r: {k: rec[r]["metrics"][k] for k in ("P", "R", "IoU")} for r in ROWS},
           "component_pairs": m["matching"]["component_pairs"], "prefiltered": m["matching"]["prefiltered"],
           "match_stats": m["matching"],  # solve outcomes, MILP node counts, CPU seconds
           "outcomes": m["pruning"]["matches_by_outcome"],
           "within": m["gt"]["within"], "across": m["gt"]["across"],
           "cosine_same_object": cos["same_object"], "cosine_different_object": cos["different_object"],
           "steps_s": rec["ours-matching"]["timings"]["steps_s"]}
    return row


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="development dataset folder (never the seed-0 test data)")
    p.add_argument("--config", default="", help="the `ours` YAML config (the variants' starting point)")
    p.add_argument("--variant", action="append", required=True, metavar="NAME:KEY=VALUE,...")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override for every variant")
    p.add_argument("--out", default="runs/matching-levers", help="evaluate3d's results folders (one per variant)")
    p.add_argument("--json", default="experiments/results/matching_levers.json")
    args = p.parse_args(argv)
    variants = parse_inputs("bench_matching_levers", args.variant, args.data)
    if variants is None:
        return 2
    rows = [run_variant(args, name, sets) for name, sets in variants]
    save_rows(args.json, rows, lambda r: (r["dataset_hash"], r["variant"]),
              "graph matching under φ1 config variants through evaluate3d (experiments/bench_matching_levers.py)")
    print(f"{'variant':<16} {'symseg IoU':>10} {'matched IoU':>11} {'prefilt':>8} {'merges':>6} {'w.P':>5} "
          f"{'w.R':>5} {'x.R':>5} {'cos same med/q75':>17} {'cos diff med/q75':>17} {'wall s':>7}")
    for r in rows:
        cs, cd, w = r["cosine_same_object"], r["cosine_different_object"], r["within"]
        t2 = r["table2"]
        print(f"{r['variant']:<16} {t2['lccp+symseg']['IoU']:>10.3f} {t2['ours-matching']['IoU']:>11.3f} "
              f"{r['prefiltered'] / max(1, r['component_pairs']):>8.3f} {w['merges']:>6} {w['precision']:>5.2f} "
              f"{w['recall']:>5.3f} {r['across']['recall']:>5.3f} {cs['median']:>8.2f}/{cs['q75']:<8.2f} "
              f"{cd['median']:>8.2f}/{cd['q75']:<8.2f} {r['wall_s']:>7.0f}")
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
