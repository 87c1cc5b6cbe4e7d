"""Rebuild the leaderboards from result files: one markdown per dataset, a bar chart, a montage.

    python -m selfseg.eval.leaderboard --results results/ --out leaderboards/

Reads ``RESULTS/scores/<dataset>/<name>/fold<k>.json`` (layout: :mod:`selfseg.eval.layout`) and
writes, per dataset, ``<dataset>.md`` (only the part between the GENERATED markers is replaced;
text around it is kept), ``<dataset>_iou.png`` (IoU per method, mean ± std over folds) and
``<dataset>_montage.png`` (a column per test frame of a few test videos: RGB, ground truth, then every 2-D
run's prediction in a row of its own; segments coloured like the ground-truth object they are matched to,
unmatched ones grey-blue). Runs that scored fewer folds than the dataset's most are marked in the chart and
the montage (``name (fold 0)``). When ``<dataset>_report.html`` (the ``inspect`` report,
:mod:`selfseg.eval.report`) lies in the output folder, the markdown links it.
Output depends only on the result files, the predictions and whether that report exists, so a rebuild is byte-identical.

Rows: Table I lists every 2-D run except ablation variants; Table III lists runs named ``ours``
and ``ours-<variant>`` (``evaluate --name ours-v2``); Table II lists runs with ``task = "3d"``.
Runs with the estimated foreground (``evaluate --foreground plane``) are named ``<method>@fg-plane``,
so they are rows of their own beside the ground-truth-foreground rows.
The paper's numbers (``shared/paper.md``) are shown in their own rows, marked *paper*; they come
from other data (the paper's real and synthetic sets), so they are context, not a comparison.
"""
from __future__ import annotations

import argparse
import io
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from selfseg.dataset import Dataset, DatasetError, read_inst
from selfseg.eval.aggregate import fmt, summarize_folds
from selfseg.eval.metrics import METRIC_KEYS, segment_metrics
from selfseg.eval.points import POINT_KEYS
from selfseg.eval.layout import (FAILED_JSON, PREDICTION_PNG, PREDICTIONS_DIR, SCHEMA_VERSION, SCORES_DIR,
                                 SCORES_JSON)
from selfseg.fileio import FileFormatError, atomic_write_bytes, atomic_write_text, hash_json, read_json

BEGIN = "<!-- BEGIN GENERATED (selfseg.eval.leaderboard; edits inside are overwritten) -->"
END = "<!-- END GENERATED -->"
LEADERBOARDS = Path(__file__).resolve().parents[1] / "leaderboards"  # the published leaderboards (default --out)
MONTAGE_FRAMES = 3
REPORT_HTML = "{dataset}_report.html"  # the `inspect` report the leaderboard links when it lies next to it
MONTAGE_TILE_W = 240

# The paper's reference numbers (Prec, Recall, IoU) for (real, synthetic), from shared/paper.md.
PAPER_TABLE1 = {
    "A. DeepLabV3+ supervised (upper bound)": ((.948, .947, .910), (.977, .932, .915)),
    "B. UOIS + RICE (sim-trained)": ((.859, .753, .711), (.963, .854, .838)),
    "C. LCCP on each test frame": ((.882, .749, .706), (.993, .815, .820)),
    "D. SD-MaskRCNN (sim-trained, depth)": ((.782, .773, .662), (.812, .751, .663)),
    "E. PiCIE": ((.427, .342, .230), (.361, .326, .158)),
    "F. STEGO": ((.318, .343, .162), (.325, .337, .142)),
    "Ours": ((.925, .911, .870), (.938, .925, .880)),
}
PAPER_TABLE2 = {
    "LCCP": ((.969, .858, .831), (.984, .771, .761)),
    "LCCP + SymSeg": ((.967, .861, .833), (.987, .768, .758)),
    "after graph matching": ((.957, .964, .923), (.978, .966, .950)),
}
PAPER_TABLE3 = {
    "V1 features of a COCO-trained model": ((.716, .665, .547), (.806, .775, .665)),
    "V2 LCCP labels, no graph matching": ((.915, .815, .776), (.935, .746, .711)),
    "V3 graph matching without pruning": ((.904, .832, .790), (.934, .800, .762)),
    "V4 exhaustive registration instead of matching": ((.915, .883, .842), (.931, .823, .782)),
    "Ours": ((.925, .911, .870), (.938, .925, .880)),
}


def _run_key(rec: dict) -> str:
    """What folds must share to be averaged into one row: config, dataset content and options (but the fold list)."""
    options = {k: v for k, v in rec.get("options", {}).items() if k != "folds"}
    return hash_json([rec["config_hash"], rec["dataset"]["content_hash"], options], n=8)


def load_results(results: Path) -> dict[str, dict[tuple[str, str], list[dict]]]:
    """{dataset folder key: {(task, name): [fold records sorted by fold]}} from ``results/scores``.

    Datasets are kept apart by their folder under ``scores/`` (the name, or name-hash when two datasets
    share a name). Folds of one run name whose config, dataset content or options differ are never
    averaged: each such run becomes its own row, ``name [run key]``."""
    out: dict[str, dict[tuple[str, str], list[dict]]] = defaultdict(lambda: defaultdict(list))
    for path in sorted(Path(results).glob(SCORES_JSON.format(dataset="*", name="*", fold="*"))):
        rec = read_json(path)
        if rec.get("schema_version") != SCHEMA_VERSION:
            raise FileFormatError(f"{path}: schema_version {rec.get('schema_version')!r}, expected {SCHEMA_VERSION}")
        out[path.parts[-3]][rec.get("task", "2d"), rec["name"]].append(rec)
    for groups in out.values():
        for (task, name), recs in list(groups.items()):
            keys = {_run_key(r) for r in recs}
            if len(keys) > 1:
                del groups[task, name]
                for r in recs:
                    groups[task, f"{name} [{_run_key(r)}]"].append(r)
    return {d: {k: sorted(v, key=lambda r: r["fold"]) for k, v in sorted(g.items())} for d, g in sorted(out.items())}


def load_failures(results: Path) -> dict[str, dict[tuple[str, str], list[dict]]]:
    """{dataset folder key: {(task, name): [failure records sorted by fold]}} from ``results/failed``: the folds
    (and 3-D rows) whose method passed a budget its config declares (:func:`selfseg.eval.protocol.record_failure`)."""
    out: dict[str, dict[tuple[str, str], list[dict]]] = defaultdict(lambda: defaultdict(list))
    for path in sorted(Path(results).glob(FAILED_JSON.format(dataset="*", name="*", fold="*"))):
        rec = read_json(path)
        if rec.get("schema_version") != SCHEMA_VERSION or "failure" not in rec:
            raise FileFormatError(f"{path}: not a failure record of schema_version {SCHEMA_VERSION}")
        out[path.parts[-3]][rec.get("task", "2d"), rec["name"]].append(rec)
    return {d: {k: sorted(v, key=lambda r: r["fold"]) for k, v in sorted(g.items())} for d, g in sorted(out.items())}


def _pm(s: dict, k: str) -> str:
    return f"{fmt(s['mean'][k])} ± {fmt(s['std'][k])}"


def _paper_rows(ref: dict, n_extra: int) -> list[str]:
    rows = []
    for label, (real, synth) in ref.items():
        for which, vals in (("real", real), ("synthetic", synth)):
            rows.append(f"| *paper, {which}:* {label} | " + " | ".join(fmt(v) for v in vals) + " |" + " |" * n_extra)
    return rows


def _is_ablation(name: str) -> bool:
    return name.startswith("ours-")


def _ranked(groups: dict, task: str, keep, keys) -> list[tuple[str, dict]]:
    rows = [(name, summarize_folds(recs, keys)) for (t, name), recs in groups.items() if t == task and keep(name)]
    return sorted(rows, key=lambda r: (-np.nan_to_num(r[1]["mean"]["IoU"], nan=-1), r[0]))


def _label(groups: dict, task: str, name: str) -> str:
    """A row's method cell: the run name, marked when a fold ran outside the sandbox (no user namespaces) or a
    user's method was given its training videos' labels (evaluate --method-needs-ground-truth)."""
    recs = groups[task, name]
    marks = ["unsandboxed"] if any(r.get("isolation") == "unsandboxed" for r in recs) else []
    if any(r.get("options", {}).get("method_needs_ground_truth") for r in recs):
        marks.append("given training labels")
    return f"**{name}**" + "".join(f" *({m})*" for m in marks)


def table1(groups: dict) -> list[str]:
    head = ["Method", "Prec", "Recall", "IoU", "IoU 95% CI", "Overlap F", "Boundary F", "% F≥.75", "ms/frame",
            "folds", "frames"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, s in _ranked(groups, "2d", lambda n: not _is_ablation(n), METRIC_KEYS):
        lo, hi = s["ci95"]["IoU"]
        lines.append(f"| {_label(groups, '2d', name)} | {_pm(s, 'P')} | {_pm(s, 'R')} | {_pm(s, 'IoU')} | {fmt(lo)}–{fmt(hi)} | "
                     f"{_pm(s, 'overlap_F')} | {_pm(s, 'boundary_F')} | {100 * s['mean']['F75']:.1f} | "
                     f"{s['ms_per_frame']:.1f} | {','.join(map(str, s['folds']))} | {s['n_frames']} |")
    return lines + _paper_rows(PAPER_TABLE1, len(head) - 4)


def _short_table(groups: dict, task: str, keep, keys, ref: dict) -> list[str]:
    head = ["Method", "Prec", "Recall", "IoU", "IoU 95% CI", "folds"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, s in _ranked(groups, task, keep, keys):
        lo, hi = s["ci95"]["IoU"]
        lines.append(f"| {_label(groups, task, name)} | {_pm(s, 'P')} | {_pm(s, 'R')} | {_pm(s, 'IoU')} | {fmt(lo)}–{fmt(hi)} | "
                     f"{','.join(map(str, s['folds']))} |")
    return lines + _paper_rows(ref, len(head) - 4)


def runs_table(groups: dict) -> list[str]:
    lines = ["| Run | Task | Method | Config hash | Dataset hash | Commit | Options |", "|---|---|---|---|---|---|---|"]
    for (task, name), recs in groups.items():
        r = recs[0]
        commit = (r["git"].get("commit") or "?")[:10] + ("+dirty" if r["git"].get("dirty") else "")
        opts = r.get("options", {})
        opt = f"stride {opts.get('frame_stride', '—')}, limit {opts.get('limit') or '—'}"
        if opts.get("poses_given"):
            opt += ", GT poses"
        if opts.get("foreground", "gt") != "gt":  # evaluate --foreground plane: its own row (run name @fg-plane)
            opt += f", {opts['foreground']} foreground"
        lines.append(f"| {name} | {task} | {r['method']} | `{r['config_hash']}` | `{r['dataset']['content_hash']}` | "
                     f"`{commit}` | {opt} |")
    return lines


def _fold_label(groups: dict, task: str, name: str) -> str:
    """``name``, or ``name (fold 0)`` / ``name (folds 0,1)`` when the run scored fewer folds than the dataset's
    most complete 2-D or 3-D run of the same task."""
    most = max(len(recs) for (t, _), recs in groups.items() if t == task)
    folds = [r["fold"] for r in groups[task, name]]
    if len(folds) >= most:
        return name
    return f"{name} ({'fold' if len(folds) == 1 else 'folds'} {','.join(str(f) for f in folds)})"


def bar_chart(groups: dict, title: str) -> bytes:
    """PNG bytes: mean IoU per 2-D run with ± std error bars; runs with fewer folds hatched and labelled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = _ranked(groups, "2d", lambda n: True, METRIC_KEYS)[::-1]
    labels = [_fold_label(groups, "2d", r[0]) for r in rows]
    fig, ax = plt.subplots(figsize=(6.5, 0.45 * max(len(rows), 1) + 1.2), dpi=100)
    bars = ax.barh(labels, [r[1]["mean"]["IoU"] for r in rows],
                   xerr=[np.nan_to_num(r[1]["std"]["IoU"]) for r in rows], color="#4c72b0", capsize=3)
    for bar, label, (name, _) in zip(bars, labels, rows):
        if label != name:
            bar.set_hatch("//")
            bar.set_facecolor("#a8b8d8")
    ax.set_xlim(0, 1)
    ax.set_xlabel("IoU (mean ± std over folds; hatched: fewer folds)")
    ax.set_title(title)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()


def palette(n: int) -> np.ndarray:
    """Deterministic distinct colours (uint8 RGB) for ids 1..n; index 0 is black."""
    import colorsys

    cols = [(0, 0, 0)] + [tuple(int(255 * c) for c in colorsys.hsv_to_rgb((i * 0.618034) % 1, 0.65, 0.95))
                          for i in range(n)]
    return np.array(cols, np.uint8)


def _colour_gt(gt: np.ndarray, pal: np.ndarray) -> np.ndarray:
    return pal[np.clip(gt.astype(np.int64), 0, len(pal) - 1)]


def _colour_pred(pred: np.ndarray, gt: np.ndarray, pal: np.ndarray) -> np.ndarray:
    """Predicted segments (inside the GT foreground) in the colour of their matched GT object."""
    pred = np.where(gt > 0, pred, 0)
    matches = segment_metrics(pred, gt, return_matches=True)["matches"]  # {gt id: pred id}
    img = np.zeros(gt.shape + (3,), np.uint8)
    img[pred > 0] = (90, 110, 140)
    for g, p in matches.items():
        img[pred == p] = pal[min(g, len(pal) - 1)]
    return img


def _tile(img: np.ndarray, label: str) -> np.ndarray:
    import cv2

    h = int(round(img.shape[0] * MONTAGE_TILE_W / img.shape[1]))
    t = cv2.resize(img, (MONTAGE_TILE_W, h), interpolation=cv2.INTER_NEAREST)
    cv2.putText(t, label[:34], (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
    return t


def _prediction_dir(results: Path, rec: dict) -> Path:
    local = results / PREDICTIONS_DIR.format(name=rec["name"], dataset=rec["dataset"].get("key", rec["dataset"]["name"]))
    return local if local.is_dir() else Path(rec.get("predictions_dir", local))


def montage(groups: dict, results: Path) -> bytes | None:
    """PNG bytes: a column per test video (its first test frame, up to 3 videos), rows RGB, ground truth and
    every 2-D run's prediction; None if the dataset folder recorded in the results is not available here."""
    import cv2

    runs = [(name, groups["2d", name]) for name, _ in _ranked(groups, "2d", lambda n: True, METRIC_KEYS)]
    if not runs:
        return None
    try:
        dataset = Dataset(runs[0][1][0]["dataset"]["root"])
    except DatasetError:
        return None
    videos = sorted({v for _, recs in runs for r in recs for v in r["per_video"]})[:MONTAGE_FRAMES]
    columns = []
    for vid in videos:
        labeled = dataset.labeled(vid)
        fid = labeled.frame_ids[0]  # frame 0 of a test video is always a test frame (stride from 0)
        gt = labeled.inst(fid)
        pal = palette(max(int(gt.max()), 1))
        tiles = [_tile(labeled.rgb(fid), f"{vid}/{fid:06d}"), _tile(_colour_gt(gt, pal), "ground truth")]
        for name, recs in runs:
            label = _fold_label(groups, "2d", name)
            path = _prediction_dir(results, recs[0]) / PREDICTION_PNG.format(video_id=vid, frame_id=fid)
            if path.is_file():
                tiles.append(_tile(_colour_pred(read_inst(path), gt, pal), label))
            else:  # not a test frame of this run's folds
                tiles.append(_tile(np.full(gt.shape + (3,), 40, np.uint8), f"{label}: not run"))
        columns.append(np.concatenate(tiles, 0))
    img = np.concatenate(columns, 1)
    ok, buf = cv2.imencode(".png", img[:, :, ::-1])
    return buf.tobytes() if ok else None


TABLES_NOTE = ("Mean ± std over folds; 95% CI by bootstrap over test videos; every 10th frame of held-out videos "
               "unless the run's options say otherwise (see *Runs*). *paper* rows: the paper's own numbers on its data.")


def tables(groups: dict, dataset: str) -> list[tuple[str, list[str]]]:
    """(title, markdown lines) of Tables I, II and III, as the leaderboard and the ``inspect`` report show them."""
    return [(f"Table I: objects in RGB images ({dataset})", table1(groups)),
            ("Table II: reconstructed point clouds (3-D)",
             _short_table(groups, "3d", lambda n: True, POINT_KEYS, PAPER_TABLE2)),
            ("Table III: ablations (runs named `ours` and `ours-<variant>`)",
             _short_table(groups, "2d", lambda n: n == "ours" or _is_ablation(n), METRIC_KEYS, PAPER_TABLE3))]


def failure_lines(failures: dict) -> list[str]:
    """A note naming the runs (:func:`load_failures` groups of one dataset) with folds or 3-D rows that failed
    under their budget: their rows above hold the other folds only, or are missing."""
    if not failures:
        return []
    return ["", "**Failed under their budget** (not scored; a row above averages its other folds only):", "",
            *(f"- {name} ({task}), fold {', '.join(str(r['fold']) for r in recs)}: {recs[0]['failure']['message']}"
              for (task, name), recs in failures.items())]


def generated_markdown(dataset: str, groups: dict, montage_file: str | None, report_file: str | None = None,
                       failures: dict | None = None) -> str:
    (t1, lines1), (t2, lines2), (t3, lines3) = tables(groups, dataset)
    fail2d, fail3d = ({k: v for k, v in (failures or {}).items() if k[0] == t} for t in ("2d", "3d"))
    lines = [BEGIN, "", f"## {t1}", "", TABLES_NOTE, "", *lines1, *failure_lines(fail2d), "",
             f"![IoU per method]({dataset}_iou.png)", "",
             f"## {t2}", "", *lines2, *failure_lines(fail3d), "", f"## {t3}", "", *lines3, "", "## Qualitative", ""]
    lines.append(f"![RGB, ground truth and predictions]({montage_file})" if montage_file
                 else "(montage not built: the dataset folder recorded in the results is not available)")
    if report_file:
        lines += ["", f"3-D report (clouds, segment graphs, matches; open the file in a browser): [{report_file}]({report_file})"]
    lines += ["", "## Runs", "", *runs_table(groups), "", END]
    return "\n".join(lines) + "\n"


def replace_generated(old: str | None, generated: str, title: str, begin: str = BEGIN, end: str = END) -> str:
    """Splice ``generated`` (which starts with ``begin`` and ends with ``end``) between those markers of ``old``
    (or a new page with ``title``); text outside them is kept."""
    if old is None:
        return f"# {title}\n\nRebuild with `python -m selfseg.eval.leaderboard --results results/ --out leaderboards/`.\n\n{generated}"
    i, j = old.find(begin), old.find(end)
    if i < 0 or j < i:
        return old.rstrip("\n") + "\n\n" + generated
    rest = old[j + len(end):]
    return old[:i] + generated + (rest[1:] if rest.startswith("\n") else rest)  # generated ends with "\n"


def build(results: str | Path, out: str | Path) -> list[Path]:
    """Write every dataset's leaderboard files; returns the paths written."""
    results, out = Path(results), Path(out)
    written = []
    failures = load_failures(results)
    for dataset, groups in load_results(results).items():
        md = out / f"{dataset}.md"
        chart = bar_chart(groups, f"IoU per method: {dataset}")
        atomic_write_bytes(out / f"{dataset}_iou.png", chart)
        written.append(out / f"{dataset}_iou.png")
        mont = montage(groups, results)
        if mont is not None:
            atomic_write_bytes(out / f"{dataset}_montage.png", mont)
            written.append(out / f"{dataset}_montage.png")
        report = REPORT_HTML.format(dataset=dataset)
        text = replace_generated(md.read_text() if md.is_file() else None,
                                 generated_markdown(dataset, groups, f"{dataset}_montage.png" if mont else None,
                                                    report if (out / report).is_file() else None,
                                                    failures.get(dataset)),
                                 f"Leaderboard: {dataset}")
        atomic_write_text(md, text)
        written.append(md)
    return written


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m selfseg.eval.leaderboard", description=__doc__.splitlines()[0])
    p.add_argument("--results", type=Path, default=Path("results"), help="results folder of `evaluate --out`")
    p.add_argument("--out", type=Path, default=LEADERBOARDS,
                   help="where the markdown goes (default: the repository's leaderboards/)")
    args = p.parse_args(argv)
    if not (args.results / SCORES_DIR).is_dir():
        print(f"build: error: {args.results / SCORES_DIR}: no results folder (run `evaluate` first)", file=sys.stderr)
        return 2
    try:
        for path in build(args.results, args.out):
            print(path)
    except (FileFormatError, KeyError) as e:
        print(f"build: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
