"""Diagnostic, not a test: can `ours`'s matching run on a dataset's segment graphs, under a budget that does not
depend on the machine's load?

    .venv/bin/python experiments/bench_matching_feasibility.py --data DIR --config configs/ours-cluttered.yaml
        --candidate NAME:key=value,... [--candidate ...] --node-limit N [--cpu-budget-s 1800]
        [--max-limit-share 0.10] [--out runs/matching-feasibility]
        [--json experiments/results/matching_feasibility.json]

The candidates (over-segmentation settings, as ``NAME:a=1,b.c=2`` overrides of the config) are tried in the
order given, and the first that qualifies is the answer (the rest are not run). Each runs ``evaluate --method
ours-v3 --folds 0`` (the real CLI, its own process): fold 0's φ1 on its own segments, then `ours`'s matching of
every pair of the fold's training scenes, in one process (``pseudo.match.workers=1``), with a MILP node limit
(``pseudo.match.node_limit``; the wall-clock ``time_limit_s`` only as a safety net far above it) and a CPU budget
(``--cpu-budget-s`` for the fold, given as ``pseudo.match.cpu_budget_per_pair_s``: it over the fold's pairs of
training scenes; counted in CPU seconds and enforced by the kernel). A candidate qualifies when
its matching finishes within the budget with at most ``--max-limit-share`` of its solved component pairs stopped
by a limit (status "time_limit": the node limit, or the safety net). The rows hold the matching statistics only:
`evaluate` is stopped as soon as the matching's file is written, so φ2 never trains and the fold is never scored.
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from common import parse_inputs, pseudo_stage, save_rows

from selfseg.dataset import Dataset
from selfseg.eval.folds import fold_split
from selfseg.eval.layout import WORK_DIR, results_key
from selfseg.fileio import read_json
from selfseg.method.pseudolabels import MATCHES_JSON

SAFETY_TIME_LIMIT_S = 600.0  # per MILP solve, wall-clock: far above what the node limit lets a solve take


def run_candidate(args, name: str, sets: list[str]) -> dict:
    """Run fold 0 of V3 for one candidate and return its row (verdict and matching statistics)."""
    run = f"feasibility-{name}"
    n_train = len(fold_split(Dataset(args.data), 0)[0])
    per_pair = args.cpu_budget_s / (n_train * (n_train - 1) / 2)  # the fold's budget over its pairs of scenes
    budget = ["pseudo.match.workers=1", f"pseudo.match.node_limit={args.node_limit}",
              f"pseudo.match.time_limit_s={SAFETY_TIME_LIMIT_S}", f"pseudo.match.cpu_budget_per_pair_s={per_pair!r}"]
    cmd = [str(Path(sys.executable).with_name("evaluate")), "--method", "ours-v3", "--name", run, "--folds", "0",
           "--data", args.data, "--out", args.out, "--quiet", "--config", args.config,
           *[a for s in [*sets, *budget] for a in ("--set", s)]]
    log = Path(args.out) / f"{run}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    fold = Path(args.out) / WORK_DIR.format(name=run, dataset=results_key(Path(args.out), Dataset(args.data)), fold=0)
    matches = pseudo_stage(fold) / MATCHES_JSON
    print(f"[{name}] {' '.join(cmd)}  (log {log})", flush=True)
    t0 = time.perf_counter()
    with open(log, "w") as f:
        # its own process group, stopped once the matching's file is written: φ2 and the score are not needed
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, start_new_session=True)
        while proc.poll() is None and not matches.is_file():
            time.sleep(5)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait()
    row = {"candidate": name, "sets": sets, "node_limit": args.node_limit, "cpu_budget_s": args.cpu_budget_s,
           "safety_time_limit_s": SAFETY_TIME_LIMIT_S, "max_limit_share": args.max_limit_share,
           "wall_s": round(time.perf_counter() - t0, 1), "data": str(Path(args.data).resolve()),
           "dataset_hash": Dataset(args.data).content_hash(), "config": args.config}
    if matches.is_file():
        stats = read_json(matches)["match_stats"]
        share = stats["time_limit_hits"] / stats["solved"] if stats["solved"] else 0.0
        row.update(match_stats=stats, limit_share=round(share, 4),
                   verdict="qualifies" if share <= args.max_limit_share else "too many solves stopped by a limit")
    elif "CPU budget" in log.read_text(errors="replace"):  # MatchBudgetError's message
        row["verdict"] = f"over the CPU budget of {args.cpu_budget_s:g} s"
    else:
        raise SystemExit(f"bench_matching_feasibility: candidate {name}: evaluate exited with {proc.returncode} "
                         f"before matching finished, and not for the budget (see {log})")
    print(f"[{name}] {row['verdict']}" + (f": {stats['time_limit_hits']} of {stats['solved']} solved pairs stopped "
                                         f"by a limit, {stats['cpu_s']:.0f} CPU-s, largest MILP "
                                         f"{stats['milp_nodes_max']} nodes" if "match_stats" in row else ""),
          flush=True)
    return row


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="development dataset folder")
    p.add_argument("--config", required=True, help="the `ours` YAML config the candidates override")
    p.add_argument("--candidate", action="append", required=True, metavar="NAME:KEY=VALUE,...",
                   help="an over-segmentation setting; tried in the order given")
    p.add_argument("--node-limit", type=int, required=True, help="MILP branch-and-bound nodes per solve")
    p.add_argument("--cpu-budget-s", type=float, default=1800.0, help="CPU seconds for the fold's matching")
    p.add_argument("--max-limit-share", type=float, default=0.10,
                   help="most solved component pairs a qualifying candidate may have stopped by a limit")
    p.add_argument("--out", default="runs/matching-feasibility", help="evaluate's results folder")
    p.add_argument("--json", default="experiments/results/matching_feasibility.json")
    args = p.parse_args(argv)
    candidates = parse_inputs("bench_matching_feasibility", args.candidate, args.data)
    if candidates is None:
        return 2
    for name, sets in candidates:
        row = run_candidate(args, name, sets)
        save_rows(args.json, [row], lambda r: (r["dataset_hash"], r["candidate"], r["node_limit"]),
                  "Matching feasibility of over-segmentation candidates (experiments/bench_matching_feasibility.py)")
        if row["verdict"] == "qualifies":
            print(f"first qualifying candidate: {name}")
            return 0
    print("no candidate qualifies")
    return 0


if __name__ == "__main__":
    sys.exit(main())
