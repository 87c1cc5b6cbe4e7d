"""Benchmark of evaluate's sandbox (bubblewrap): what it costs to start, and what it adds to a whole run.

    .venv/bin/python bench/bench_sandbox.py --data data/tiny [--method depth-clustering] [--runs 3]
        [--starts 20] [--out bench/results/sandbox.json]

* start-up: the interpreter doing nothing (``python -I -S -c pass``) inside the sandbox every method gets
  (the same mounts and namespaces) and as a plain child process; the difference is bubblewrap's cost.
  Median of ``--starts`` starts each.
* ``evaluate --method M --data DATA`` (3 folds, a fresh ``--out`` each run) as a user runs it, sandboxed and
  unsandboxed (``SELFSEG_BWRAP`` pointing at no binary: the plain child process of the fallback); median of
  ``--runs`` runs each. A sandboxed run starts ``1 + folds`` sandboxes (describe, then each fold).
"""
from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import bench_parser, write_result

from selfseg.eval.layout import N_FOLDS
from selfseg.eval.sandbox import BWRAP_ENV, bwrap_argv, base_mounts, bwrap_binary, sandbox_unavailable

NO_BWRAP = "/nonexistent/bwrap"


def _median_ms(argv: list[str], n: int) -> float:
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        subprocess.run(argv, check=True)
        times.append(1000 * (time.perf_counter() - t0))
    return statistics.median(times)


def _evaluate_s(method: str, data: Path, sandboxed: bool, n: int) -> float:
    env = {**os.environ, **({} if sandboxed else {BWRAP_ENV: NO_BWRAP})}
    times = []
    for _ in range(n):
        with tempfile.TemporaryDirectory() as tmp:
            argv = [sys.executable, "-m", "selfseg.eval.cli", "--method", method, "--data", str(data), "--out", tmp,
                    "--quiet"]
            t0 = time.perf_counter()
            subprocess.run(argv, check=True, env=env, capture_output=True)
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    p = bench_parser(__doc__, "sandbox.json")
    p.add_argument("--data", type=Path, required=True, help="a dataset folder (the tiny preset)")
    p.add_argument("--method", default="depth-clustering")
    p.add_argument("--runs", type=int, default=3, help="evaluate runs per setting (median)")
    p.add_argument("--starts", type=int, default=20, help="sandbox starts (median)")
    args = p.parse_args(argv)
    reason = sandbox_unavailable()
    if reason is not None:
        print(f"bench_sandbox: no sandbox can be started here ({reason})", file=sys.stderr)
        return 2

    nothing = [sys.executable, "-I", "-S", "-c", "pass"]
    sandbox = bwrap_argv(bwrap_binary(), list(base_mounts()), os.getcwd())
    start = {"plain_ms": _median_ms(nothing, args.starts), "sandbox_ms": _median_ms(sandbox + nothing, args.starts)}
    start["bwrap_ms"] = start["sandbox_ms"] - start["plain_ms"]
    run = {"sandbox_s": _evaluate_s(args.method, args.data, True, args.runs),
           "unsandboxed_s": _evaluate_s(args.method, args.data, False, args.runs)}
    run["overhead_s"] = run["sandbox_s"] - run["unsandboxed_s"]
    run["overhead_per_process_s"] = run["overhead_s"] / (1 + N_FOLDS)

    print(f"{'sandbox start-up (python -I -S -c pass)':44s} plain {start['plain_ms']:7.1f} ms   sandboxed "
          f"{start['sandbox_ms']:7.1f} ms   bwrap {start['bwrap_ms']:6.1f} ms   (median of {args.starts})")
    print(f"{f'evaluate --method {args.method} ({N_FOLDS} folds)':44s} plain {run['unsandboxed_s']:7.2f} s    "
          f"sandboxed {run['sandbox_s']:7.2f} s    +{run['overhead_s']:.2f} s ({run['overhead_per_process_s']:.2f} s per "
          f"process, {1 + N_FOLDS} processes; median of {args.runs})")
    write_result(args.out, {"start_up": {k: round(v, 2) for k, v in start.items()},
                            "evaluate": {k: round(v, 3) for k, v in run.items()},
                            "method": args.method, "data": str(args.data), "runs": args.runs, "starts": args.starts,
                            "bwrap": subprocess.run([bwrap_binary(), "--version"], capture_output=True,
                                                    text=True).stdout.strip()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
