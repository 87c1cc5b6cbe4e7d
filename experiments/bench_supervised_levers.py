"""Diagnostic, not a test: the supervised bound (or another learned method) under named config variants.

    .venv/bin/python experiments/bench_supervised_levers.py --data DIR --config configs/supervised-calibrated.yaml
        --variant NAME:key=value,key=value ... [--method supervised] [--folds 0] [--set KEY=VALUE ...]
        [--out runs/levers] [--json experiments/results/supervised_levers.json] [--networks-of NAME]

Each variant runs ``evaluate --method METHOD --data DIR --config CONFIG --set ... --folds FOLDS --name
METHOD@NAME --out OUT`` (the real CLI and protocol, in its own process), one variant after the other, then
reads the fold records back: IoU per fold, their mean, and the wall time of the call. ``--set`` applies to
every variant, the variant's own ``key=value`` pairs after it (``NAME`` alone: the config as it is; a value
holding a comma is written in brackets, ``train.crop=[160,192]``). Run it on a development dataset, never on
the seed-0 test folds. ``evaluate`` resumes finished folds and the trained networks are cached under
OUT/work, so a re-run only scores what is missing. The JSON keeps the rows of earlier calls (keyed by
dataset, method, variant and folds) and replaces those run again. ``--networks-of NAME`` compares inference
options on the same networks: the trained networks of variant NAME (same method, OUT and folds) are copied into
each variant's work folder first, so a variant that changes no training setting finds its network trained (one
that does gets another network key and trains its own).
"""
from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from common import parse_inputs, run_variant_command, save_rows

from selfseg.dataset import Dataset
from selfseg.eval.layout import SCORES_JSON, WORK_DIR, results_key
from selfseg.fileio import read_json


def copy_networks(args, source: str, name: str, folds: list[int]) -> None:
    """Copy variant ``source``'s trained networks (``net-*`` folders with weights) into variant ``name``'s fold work
    folders, leaving networks already there alone."""
    key = results_key(Path(args.out), Dataset(args.data))
    for k in folds:
        src, dst = (Path(args.out) / WORK_DIR.format(name=f"{args.method}@{n}", dataset=key, fold=k)
                    for n in (source, name))
        nets = [d for d in sorted(src.glob("net-*")) if (d / "weights.pt").is_file()]
        if not nets:
            raise SystemExit(f"bench_supervised_levers: {src}: no trained network of variant {source!r}, fold {k}")
        for d in nets:
            if not (dst / d.name).exists():
                shutil.copytree(d, dst / d.name)


def run_variant(args, name: str, sets: list[str], folds: list[int]) -> dict:
    """Run ``evaluate`` for one variant and read its fold records back."""
    run_name = f"{args.method}@{name}"
    if args.networks_of and name != args.networks_of:
        copy_networks(args, args.networks_of, name, folds)
    cmd = [sys.executable, "-m", "selfseg.eval.cli", "--method", args.method, "--data", args.data, "--folds",
           ",".join(map(str, folds)), "--name", run_name, "--out", args.out, "--quiet"]
    wall_s = run_variant_command("bench_supervised_levers", name, cmd, args.config, [*args.overrides, *sets])
    ds = Dataset(args.data)
    key = results_key(Path(args.out), ds)
    recs = [read_json(Path(args.out) / SCORES_JSON.format(dataset=key, name=run_name, fold=k)) for k in folds]
    iou = [r["metrics"]["IoU"] for r in recs]
    return {"variant": name, "method": args.method, "data": str(Path(args.data).resolve()),
            "dataset_hash": ds.content_hash(), "config": args.config, "sets": [*args.overrides, *sets],
            "folds": folds, "iou_per_fold": iou, "iou_mean": sum(iou) / len(iou),
            "precision_mean": sum(r["metrics"]["P"] for r in recs) / len(recs),
            "recall_mean": sum(r["metrics"]["R"] for r in recs) / len(recs),
            "fit_s_per_fold": [r["timings"]["fit_s"] for r in recs], "wall_s": round(wall_s, 1),
            "commit": recs[0]["git"]["commit"], **({"networks_of": args.networks_of} if args.networks_of else {})}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="development dataset folder (never the seed-0 test folds)")
    p.add_argument("--method", default="supervised")
    p.add_argument("--config", default="", help="the method's YAML config (the variants' starting point)")
    p.add_argument("--variant", action="append", required=True, metavar="NAME:KEY=VALUE,...")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override for every variant (e.g. train.threads=1)")
    p.add_argument("--folds", default="0,1,2")
    p.add_argument("--out", default="runs/levers", help="evaluate's results folder")
    p.add_argument("--json", default="experiments/results/supervised_levers.json")
    p.add_argument("--networks-of", default="", metavar="NAME",
                   help="start every other variant from variant NAME's trained networks (inference options)")
    args = p.parse_args(argv)
    variants = parse_inputs("bench_supervised_levers", args.variant, args.data)
    try:
        folds = [int(k) for k in args.folds.split(",")]
    except ValueError:
        print(f"bench_supervised_levers: --folds {args.folds!r}: not comma-separated fold numbers", file=sys.stderr)
        return 2
    if variants is None:
        return 2
    rows = [run_variant(args, name, sets, folds) for name, sets in variants]
    ident = lambda r: (r["dataset_hash"], r["method"], r["variant"], tuple(r["folds"]))  # noqa: E731
    save_rows(args.json, rows, ident,
              "IoU of named config variants through evaluate (experiments/bench_supervised_levers.py)")
    print(f"{'variant':<24} {'method':<12} {'folds':<6} {'IoU per fold':<22} {'mean':>5} {'P':>5} {'R':>5} "
          f"{'wall s':>7}  sets")
    for r in rows:
        per = " / ".join(f"{x:.3f}" for x in r["iou_per_fold"])
        print(f"{r['variant']:<24} {r['method']:<12} {','.join(map(str, r['folds'])):<6} {per:<22} "
              f"{r['iou_mean']:.3f} {r['precision_mean']:.3f} {r['recall_mean']:.3f} {r['wall_s']:>7.0f}  "
              f"{' '.join(r['sets'])}")
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
