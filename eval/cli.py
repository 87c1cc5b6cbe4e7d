"""The evaluation stage's commands. ``evaluate``: score a registered method, or one of your own, on a dataset
under the paper's protocol; ``evaluate3d``: Table II (:mod:`selfseg.eval.table2`).

    evaluate --method NAME|package.module:ClassName --data DIR [--config FILE] [--set key=value ...] [--folds 0,1,2]
             [--frame-stride 10] [--limit N] [--predictions DIR] [--name NAME] [--poses-given]
             [--method-needs-ground-truth] [--trust-method] [--replace]
             [--out results/] [--list-methods] [--executor local|ray] [--ray-address auto|HOST:PORT]
    evaluate3d --data DIR [--config FILE] [--set key=value ...] [--out results/]
               [--rows lccp,lccp+symseg,ours-matching,gt-merging] [--stats] [--quiet] [--executor local|ray]

Writes results under ``--out`` (layout in :mod:`selfseg.eval.layout`) and prints a table. The method's code
runs only in its own sandboxed process (:mod:`selfseg.eval.sandbox`), never in this one.
Errors in the inputs (unknown method, missing dataset, bad config or predictions) print one
message naming the file or option and exit with status 2. A fold whose method passes a compute budget its config
declares (e.g. ``ours``'s matching CPU) is recorded as failed (``failed/…``, not scored, not run again), the other
folds still run, and the exit status is 3 (``evaluate3d``: the same for its ``ours-matching`` row).
"""
from __future__ import annotations

import argparse
import concurrent.futures as cf
import errno
import shutil
import sys
from pathlib import Path

from selfseg.config import ConfigError
from selfseg.dataset import Dataset, DatasetError
from selfseg.eval.aggregate import fmt, summarize_folds
from selfseg.eval.folds import EvalOptions
from selfseg.eval.layout import FAILED_JSON, N_FOLDS, RUN_SCORES_DIR, results_key
from selfseg.eval.protocol import EXIT_OVER_BUDGET, run_fold
from selfseg.eval.resume import failed_fold, finished_fold, retire_run, run_conflict
from selfseg.eval.sandbox import MethodRef, SandboxError, describe_method, sandbox_unavailable
from selfseg.eval.scoring import MethodOutputError
from selfseg.executor import ExecutorConfig, ExecutorError, add_executor_arguments, executor_config, shared_executor
from selfseg.fileio import BusyError, FileFormatError
from selfseg.guard import GroundTruthAccessError
from selfseg.method_api import BudgetExceededError
from selfseg.registry import UnknownMethodError, get_method_class, method_names

TABLE_KEYS = ("P", "R", "IoU", "overlap_F", "boundary_F", "F75")


def _parse_folds(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"--folds must be comma-separated integers, got {text!r}") from None


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="evaluate", description="Score a segmentation method under the paper's protocol "
                                "(3-fold CV over videos, every 10th test frame, GT foreground given).")
    p.add_argument("--method", help="registered method name (see --list-methods), or package.module:ClassName "
                   "of your own method on PYTHONPATH")
    p.add_argument("--data", type=Path, help="dataset folder")
    p.add_argument("--config", type=Path, help="YAML file with the method's config")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value (repeatable), e.g. --set distance_m=0.02")
    p.add_argument("--folds", type=_parse_folds, default=tuple(range(N_FOLDS)), help="folds to run (default 0,1,2)")
    p.add_argument("--frame-stride", type=int, default=10, help="score every N-th frame of a test video (default 10)")
    p.add_argument("--limit", type=int, help="at most N test frames per held-out video (quick runs)")
    p.add_argument("--predictions", type=Path, help="folder of predictions for --method external "
                   "(<video_id>/<frame_id:06d>.png)")
    p.add_argument("--name", help="name of this run in results and leaderboards (default: the method name)")
    p.add_argument("--poses-given", action="store_true", help="give methods ground-truth camera poses (ablation)")
    p.add_argument("--method-needs-ground-truth", action="store_true",
                   help="give your own method (package.module:ClassName) the fold's training videos' labels, never "
                   "the test videos'; recorded, and the run is named <name>@train-labels")
    p.add_argument("--trust-method", action="store_true",
                   help="where no sandbox can be started (no user namespaces or no bwrap), run your own method anyway, "
                   "in a plain process that can read anything you can (results marked unsandboxed)")
    p.add_argument("--foreground", choices=("gt", "plane"), default="gt",
                   help="foreground given to methods: gt (the paper's protocol) or plane (estimated from depth by "
                   "removing the support plane; scored on the GT foreground; run name gets '@fg-plane')")
    p.add_argument("--out", type=Path, default=Path("results"), help="results folder (default results/)")
    p.add_argument("--replace", action="store_true",
                   help="replace a run of the same name made with another config or options (its folds and "
                   "predictions go to OUT/replaced/ and are deleted once this run finished); without it, such a "
                   "run is refused")
    p.add_argument("--list-methods", action="store_true", help="list registered methods and exit")
    add_executor_arguments(p, "folds (one task per fold: the method's process, its scoring and its files)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def format_table(name: str, records: list[dict]) -> str:
    """Per-fold rows, then mean ± std over folds and the bootstrap 95% CI of each metric."""
    head = ["fold", "frames", *TABLE_KEYS, "ms/frame"]
    rows = [[str(r["fold"]), str(r["metrics"]["n_frames"]), *(fmt(r["metrics"][k]) for k in TABLE_KEYS),
             f"{r['timings']['ms_per_frame']:.1f}"] for r in records]
    s = summarize_folds(records)
    rows.append(["mean±std", str(s["n_frames"]), *(f"{fmt(s['mean'][k])}±{fmt(s['std'][k])}" for k in TABLE_KEYS),
                 f"{s['ms_per_frame']:.1f}"])
    rows.append(["95% CI", "", *(f"{fmt(s['ci95'][k][0])}–{fmt(s['ci95'][k][1])}" for k in TABLE_KEYS), ""])
    widths = [max(len(x) for x in col) for col in zip(head, *rows)]
    line = lambda cells: "  ".join(c.rjust(w) for c, w in zip(cells, widths))  # noqa: E731
    return "\n".join([f"{name} on {records[0]['dataset']['name']}", line(head), *(line(r) for r in rows)])


def method_ref(args: argparse.Namespace, overrides: list[str]) -> tuple[MethodRef, dict]:
    """The method ``--method`` names and its resolved config, described by its own process (sandboxed where a
    sandbox can start; else refused for a method of your own unless ``--trust-method``, said in one line)."""
    user = ":" in args.method
    if args.method_needs_ground_truth and not user:
        raise ConfigError(f"--method-needs-ground-truth is for a method of your own; {args.method!r} is registered "
                          "and its registry entry says which labels it gets")
    reason = sandbox_unavailable()
    if reason is not None and user and not args.trust_method:
        raise SandboxError(f"no sandbox can be started here ({reason}), so a method of your own runs only with "
                           "--trust-method (it can then read anything you can, ground truth included)")
    if reason is not None:
        print(f"evaluate: no sandbox can be started here ({reason}); {args.method} runs unsandboxed, with the "
              "in-process check only (its results are marked unsandboxed)", file=sys.stderr)
    return describe_method(args.method, args.config, overrides, reason is None, args.data, args.out)


def run_folds_as_tasks(where: ExecutorConfig, ref: MethodRef, config: dict, dataset: Dataset, folds: list[int],
                       out: Path, options: EvalOptions, quiet: bool) -> dict[int, dict]:
    """Run ``folds`` as tasks of the executor ``where`` names (e.g. Ray: one task per fold, reserving
    ``ray_cpus_per_task`` CPUs). A task is what :func:`run_fold` does here: the method in its own sandboxed
    process (no network, so it cannot reach the cluster), then scoring and the result files, written to
    ``out`` (which every node must see). Returns {fold: record, or the BudgetExceededError of a fold that passed
    its budget}; Ctrl-C cancels the tasks."""
    ex = shared_executor(where, out)
    try:
        futures = {ex.submit(run_fold, ref, config, dataset, k, out, options, False): k for k in folds}
        records = {}
        for f in cf.as_completed(futures):
            try:
                records[futures[f]] = f.result()
            except BudgetExceededError as e:
                records[futures[f]] = e
            if not quiet:
                print(f"fold {futures[f]}: ended ({len(records)}/{len(folds)})", file=sys.stderr)
    except BaseException:
        ex.shutdown(wait=False, cancel_futures=True)
        raise
    ex.shutdown()
    return records


def run(args: argparse.Namespace) -> int:
    if args.list_methods:
        for name in method_names():
            try:
                doc = (get_method_class(name).__doc__ or "").strip().splitlines()[0]
            except Exception as e:  # a broken adapter must not hide the others
                doc = f"(cannot be imported: {e!r})"
            print(f"{name:20s} {doc}")
        return 0
    if not args.method or not args.data:
        raise ConfigError("--method and --data are required (or use --list-methods)")
    overrides = list(args.overrides)
    if args.predictions is not None:
        if args.method != "external":
            raise ConfigError(f"--predictions is only for --method external, not {args.method!r}")
        overrides.append(f"predictions={args.predictions}")
    ref, config = method_ref(args, overrides)
    suffix = ("@fg-plane" if args.foreground == "plane" else "") + ("@train-labels" if args.method_needs_ground_truth
                                                                     else "")
    try:
        options = EvalOptions(folds=args.folds, frame_stride=args.frame_stride, limit=args.limit,
                              name=args.name or (ref.name + suffix if suffix else None), poses_given=args.poses_given,
                              foreground=args.foreground, method_needs_ground_truth=args.method_needs_ground_truth)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    dataset = Dataset(args.data)
    if not dataset.has_labels():
        raise DatasetError(f"{dataset.root}: has no ground truth (no scene_gt.json / mask_inst/), so evaluate cannot "
                           "score it; use train and segment for unlabeled recordings")
    where = executor_config(args, args.config)
    conflict = run_conflict(args.out, dataset, ref.name, config, options)
    if conflict is not None and not args.replace:
        raise ConfigError(f"{conflict}; name this one with --name, or give --replace to replace that run")
    replaced = retire_run(args.out, dataset, options.name or ref.name) if conflict is not None else None
    records: dict[int, dict | Path | BudgetExceededError | None] = {}
    for k in options.folds:  # a fold finished by an earlier run with the same keys is reused (resume)
        records[k] = finished_fold(ref, config, dataset, k, args.out, options)
        if records[k] is not None and not args.quiet:
            print(f"fold {k}: reusing the finished result of an identical run", file=sys.stderr)
        elif records[k] is None:  # one that failed under its budget is not run again: it would fail again
            records[k] = failed_fold(ref, config, dataset, k, args.out, options)
    todo = [k for k in options.folds if records[k] is None]
    if where.distributed and todo:
        records.update(run_folds_as_tasks(where, ref, config, dataset, todo, args.out, options, args.quiet))
    else:  # plain local runs: one fold after the other, from this process; a fold over its budget ends alone
        for k in todo:
            try:
                records[k] = run_fold(ref, config, dataset, k, args.out, options, progress=not args.quiet)
            except BudgetExceededError as e:
                records[k] = e
    if replaced is not None:
        shutil.rmtree(replaced, ignore_errors=True)
    name = options.name or ref.name
    done = [r for r in records.values() if isinstance(r, dict)]
    if done:
        print(format_table(name, done))
    print("results: " + str(args.out / RUN_SCORES_DIR.format(dataset=results_key(args.out, dataset), name=name)))
    failed = {k: r for k, r in records.items() if not isinstance(r, dict)}
    for k, r in failed.items():
        path = args.out / FAILED_JSON.format(dataset=results_key(args.out, dataset), name=name, fold=k)
        why = f"{r}" if isinstance(r, BudgetExceededError) else "in an earlier identical run; not run again"
        print(f"evaluate: fold {k} of {name!r} failed under its budget: {why} (recorded in {path}; delete that "
              "file to run the fold again)", file=sys.stderr)
    return EXIT_OVER_BUDGET if failed else 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return run(args)
    except KeyboardInterrupt:
        print("evaluate: interrupted; finished folds are kept, run the same command to resume", file=sys.stderr)
        return 130
    except GroundTruthAccessError as e:
        print(f"evaluate: error: method {args.method!r} tried to read ground truth ({args.out / 'rejected'}): {e}",
              file=sys.stderr)
    except (UnknownMethodError, ConfigError, DatasetError, FileFormatError, FileNotFoundError, MethodOutputError,
            ExecutorError, SandboxError, BusyError) as e:
        print(f"evaluate: error: {e}", file=sys.stderr)
    except OSError as e:
        if e.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        print(f"evaluate: error: {e.filename or args.out}: no space left; finished folds are kept", file=sys.stderr)
        return 1
    return 2


def evaluate3d_parser() -> argparse.ArgumentParser:
    from selfseg.eval.table2 import ROWS, STATS_JSON

    p = argparse.ArgumentParser(prog="evaluate3d", description="Table II: score the pipeline's 3-D segmentations of "
                                "the reconstructed scenes against the ground-truth object points.")
    p.add_argument("--data", type=Path, required=True, help="dataset folder")
    p.add_argument("--config", type=Path, help="YAML file with the `ours` config (e.g. configs/ours-tiny.yaml)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value (repeatable)")
    p.add_argument("--rows", default=",".join(ROWS), help=f"comma-separated rows (default {','.join(ROWS)})")
    p.add_argument("--out", type=Path, default=Path("results"), help="results folder (default results/)")
    p.add_argument("--quiet", action="store_true", help="no progress bars while scoring (pipeline stages keep theirs)")
    p.add_argument("--stats", action="store_true",
                   help="instead of Table II: the data statistics (touching objects, LCCP and LCCP + SymSeg P/R/IoU, "
                        "the gt-merging ceiling, segments per object, where recall goes, reconstruction error, "
                        "camera distance, object size in pixels) per video and overall, written to "
                        "OUT/" + STATS_JSON)
    add_executor_arguments(p, "per-video stages (reconstruction, over-segmentation), matching and registrations")
    return p


def evaluate3d_main(argv: list[str] | None = None) -> int:
    """``evaluate3d`` (:mod:`selfseg.eval.table2`, imported only here: ``evaluate`` never loads the pipeline)."""
    from selfseg.eval import table2

    try:
        return table2.run(evaluate3d_parser().parse_args(argv))
    except GroundTruthAccessError as e:
        print(f"evaluate3d: error: the pipeline tried to read ground truth: {e}", file=sys.stderr)
    except (ConfigError, DatasetError, FileFormatError, FileNotFoundError, ExecutorError) as e:
        print(f"evaluate3d: error: {e}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
