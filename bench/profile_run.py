"""Where a benchmark run's time goes: each step's wall and CPU time and peak memory, each method's training,
inference and scoring, and the pipeline's stages (reconstruction, over-segmentation, φ training, matching,
pruning with registration).

    .venv/bin/python bench/profile_run.py RUN_DIR [--out bench/results/profile_calibrated.json]

RUN_DIR is a ``scripts/benchmark.sh`` run folder. Read from it:

- ``timings.tsv``: a row per step (name, wall s; CPU s and peak MB where the step wrapper recorded them), and
  ``total``, the wall time of the invocation that finished the run (a resumed run counts only its last part, so
  the JSON also sums the steps' wall times, every attempt of each, as ``steps_wall_sum_s``);
- ``results/scores``: per fold, ``fit_s``, and inference and scoring ms per frame times the fold's test frames;
- ``results/work``: the stage files. Reconstruction and over-segmentation timings per video (``report.json``),
  every network's ``training_log.json`` (φ1 under ``_stages/*/phi1``, the methods' own under their fold's
  folder), the pseudo stage's timings (``diagnostics.json``).

Stages shared by several runs (reconstruction, over-segmentation; φ1 with V2) ran once, in whichever run came
first, and are counted once. A field a run's code did not record yet is null.
"""
from __future__ import annotations

import csv
import sys
from collections import defaultdict
from pathlib import Path

from common import bench_parser, write_result

from selfseg.eval.layout import SCORES_DIR
from selfseg.fileio import FileFormatError, read_json


def read_steps(tsv: Path) -> tuple[list[dict], float | None]:
    """The rows of ``timings.tsv`` (a repeated step keeps each run of it) and the ``total`` row's wall s."""
    steps, total = [], None
    with open(tsv, newline="") as f:
        for n, row in enumerate(csv.reader(f, delimiter="\t"), 1):
            if len(row) < 2:
                raise FileFormatError(f"{tsv}:{n}: expected NAME<TAB>WALL_S[<TAB>CPU_S<TAB>PEAK_MB], got {row!r}")
            cells = [float(c) if c else None for c in row[1:4]] + [None] * (4 - len(row))
            if row[0] == "total":
                total = cells[0]
            else:
                steps.append({"step": row[0], "wall_s": cells[0], "cpu_s": cells[1], "peak_mb": cells[2]})
    return steps, total


def method_times(scores: Path) -> dict:
    """Per run name: folds, fit, inference and scoring seconds summed over its folds, and test frames."""
    out = {}
    for run in sorted(p for p in scores.glob("*/*") if p.is_dir()):
        folds = [read_json(f) for f in sorted(run.glob("fold*.json"))]
        if not folds:
            continue
        frames = [r["metrics"].get("n_frames", 0) for r in folds]
        t = [r.get("timings", {}) for r in folds]
        out[run.name] = {
            "folds": len(folds), "test_frames": sum(frames),
            "fit_s": round(sum(x.get("fit_s", 0.0) for x in t), 1),
            "inference_s": round(sum(x.get("ms_per_frame", 0.0) * n / 1000 for x, n in zip(t, frames)), 1),
            "scoring_s": round(sum(x.get("score_s", x.get("score_ms_per_frame", 0.0) * n / 1000)
                                   for x, n in zip(t, frames)), 1)}
    return out


def _sum_timings(reports: list[dict]) -> dict:
    total: dict[str, float] = defaultdict(float)
    for r in reports:
        for k, v in r.get("timings_s", {}).items():
            total[k] += v
    return {"videos": len(reports), "with_timings": sum("timings_s" in r for r in reports),
            **{k: round(v, 1) for k, v in sorted(total.items())}}


def stage_times(work: Path) -> dict:
    """Reconstruction and over-segmentation summed over videos, each training log and each pseudo stage."""
    training = []
    for log in sorted(work.rglob("training_log.json")):
        rec = read_json(log)
        training.append({"path": str(log.parent.relative_to(work)), "seconds": rec.get("seconds_this_session"),
                         "steps": rec.get("steps"), "images_per_s": rec.get("images_per_s")})
    pseudo = [{"path": str(d.parent.relative_to(work)), **read_json(d).get("timings_s", {})}
              for d in sorted(work.rglob("diagnostics.json"))]
    return {"reconstruction": _sum_timings([read_json(p) for p in sorted(work.rglob("recon/*/report.json"))]),
            "overseg": _sum_timings([read_json(p) for p in sorted(work.rglob("overseg/*/report.json"))]),
            "training": training, "pseudo": pseudo}


def _row(cells: list) -> str:
    return f"{cells[0]:<24}" + "".join(f"{'–' if c is None else c:>10}" for c in cells[1:])


def main() -> int:
    p = bench_parser(__doc__, "profile_calibrated.json")
    p.add_argument("run", type=Path, metavar="RUN_DIR", help="a scripts/benchmark.sh run folder")
    args = p.parse_args()
    tsv = args.run / "timings.tsv"
    if not tsv.is_file():
        print(f"profile_run: error: {tsv}: missing; {args.run} is not a scripts/benchmark.sh run folder", file=sys.stderr)
        return 2
    try:
        steps, total = read_steps(tsv)
        methods = method_times(args.run / "results" / SCORES_DIR)
        stages = stage_times(args.run / "results" / "work")
    except FileFormatError as e:
        print(f"profile_run: error: {e}", file=sys.stderr)
        return 2
    print(_row(["step", "wall s", "CPU s", "peak MB", "fit s", "infer s", "score s"]))
    for s in steps:
        m = methods.get(s["step"], {})
        print(_row([s["step"], s["wall_s"], s["cpu_s"], s["peak_mb"], m.get("fit_s"), m.get("inference_s"),
                    m.get("scoring_s")]))
    steps_sum = sum(s["wall_s"] or 0 for s in steps)
    print(f"total wall: {total if total is not None else 'not recorded'} s; sum of step walls "
          f"{steps_sum:.0f} s (the jobs run two at a time)")
    rec, ovs = stages["reconstruction"], stages["overseg"]
    print(f"reconstruction: {rec['videos']} videos, {rec.get('total_s', 0):.0f} s; over-segmentation: "
          f"{ovs.get('overseg_s', 0) + ovs.get('graph_s', 0) + ovs.get('maps_s', 0):.0f} s "
          f"({ovs['with_timings']} of {ovs['videos']} videos timed)")
    print(f"network training: {sum(t['seconds'] or 0 for t in stages['training']):.0f} s in {len(stages['training'])} "
          f"runs; pseudo stages: {len(stages['pseudo'])}")
    write_result(args.out, {"what": "where a scripts/benchmark.sh run's time goes (bench/profile_run.py)",
                            "run": str(args.run.resolve()), "total_wall_s": total,
                            "steps_wall_sum_s": steps_sum, "steps": steps,
                            "methods": methods, "stages": stages})
    return 0


if __name__ == "__main__":
    sys.exit(main())
