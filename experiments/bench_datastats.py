"""The data-statistics report of several datasets side by side: one line per dataset.

    .venv/bin/python experiments/bench_datastats.py \\
        --data tiny=runs/demo/data:configs/ours-tiny.yaml \\
        --data benchmark=runs/benchmark/data:configs/ours-benchmark.yaml \\
        --data calibrated=runs/calibrated/data:configs/ours-calibrated.yaml \\
        [--work runs/datastats] [--out experiments/results/datastats.json]

Each ``NAME=DATASET:CONFIG`` runs ``evaluate3d --stats`` (:func:`selfseg.eval.table2.run_stats`; stages cached
under ``--work``) with that dataset's ``ours`` config, whose reconstruction and over-segmentation settings are
the ones the statistics describe. The paper's synthetic Table II row is printed beside them: LCCP
P .984 / R .771 / IoU .761, LCCP + SymSeg .987 / .768 / .758, after matching .978 / .966 / .950.
The JSON keeps the datasets of earlier runs that this one does not name (each entry records its own command),
so one dataset's line can be refreshed alone; the table prints every entry.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from selfseg.config import load_config
from selfseg.dataset import Dataset
from selfseg.eval.datastats import stats_line, stats_table
from selfseg.eval.provenance import machine
from selfseg.eval.table2 import run_stats
from selfseg.fileio import read_json, write_json
from selfseg.method.pipeline import OursConfig

PAPER = "paper (synthetic): LCCP .984 / .771 / .761, LCCP + SymSeg .987 / .768 / .758, after matching IoU .950"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", action="append", required=True, metavar="NAME=DATASET:CONFIG")
    p.add_argument("--work", type=Path, default=Path("runs/datastats"))
    p.add_argument("--out", type=Path, default=Path("experiments/results/datastats.json"))
    args = p.parse_args(argv)
    results = read_json(args.out)["results"] if args.out.is_file() else {}
    for item in args.data:
        name, _, rest = item.partition("=")
        data, _, config = rest.partition(":")
        if not name or not data:
            p.error(f"--data {item!r}: expected NAME=DATASET[:CONFIG]")
        t0 = time.perf_counter()
        rec = run_stats(Dataset(data), load_config(OursConfig, Path(config) if config else None), args.work)
        results[name] = {"data": data, "config": config, "content_hash": rec["dataset"]["content_hash"],
                         "overall": rec["overall"], "seconds": round(time.perf_counter() - t0, 1),
                         "argv": sys.argv[1:], "machine": machine()}
    print(stats_table([stats_line(name, r["overall"]) for name, r in results.items()], first="dataset"))
    print(PAPER)
    write_json(args.out, {"results": results})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
