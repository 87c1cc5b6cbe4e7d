"""Resuming and refusing runs: a fold finished by an identical earlier run is reused (:func:`finished_fold`), one
that failed under its budget in an identical earlier run is not run again (:func:`failed_fold`), and a run name holds one run: ``evaluate`` refuses a run whose method, config or options differ from those already filed
under its name (:func:`run_conflict`) unless ``--replace`` is given (:func:`retire_run`)."""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from selfseg.config import config_hash, to_dict
from selfseg.dataset import Dataset
from selfseg.eval.folds import EvalOptions, select_test_frames
from selfseg.eval.layout import (FAILED_JSON, PREDICTION_PNG, PREDICTIONS_DIR, REPLACED_DIR, RUN_FAILED_DIR,
                                 RUN_SCORES_DIR, SCORES_JSON, results_key)
from selfseg.eval.provenance import git_info, run_key
from selfseg.eval.sandbox import MethodRef
from selfseg.fileio import read_json
from selfseg.method_api import Method


def _resume_key(record: dict) -> dict:
    return {**run_key(record), "options": {k: v for k, v in record["options"].items() if k != "folds"}}


def _wanted_key(method_cls: MethodRef | type[Method], config, dataset: Dataset, options: EvalOptions) -> dict:
    """The :func:`_resume_key` a record of this run would have if made now, from this checkout."""
    return {"method": method_cls.name, "config_hash": config_hash(config),
            "options": {k: v for k, v in dataclasses.asdict(options).items() if k != "folds"},
            "dataset": dataset.content_hash(), "commit": git_info()["commit"]}


def _differences(old, new, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two JSON-like dicts, as ``key old → new``."""
    if isinstance(old, dict) and isinstance(new, dict):
        return [d for k in sorted(set(old) | set(new), key=str)
                for d in _differences(old.get(k), new.get(k), f"{prefix}{k}.")]
    return [] if old == new else [f"{prefix[:-1]} {old!r} → {new!r}"]


def run_conflict(out: Path, dataset: Dataset, method: str, config, options: EvalOptions) -> str | None:
    """Why a run with these settings would mix with the run already filed under its name in ``out`` (another
    method, config or protocol options: each fold of a run must share them), or None. The dataset is not
    compared: another dataset's content is filed under a key of its own (:func:`results_key`)."""
    name = options.name or method
    new = {"method": method, "config": to_dict(config),
           "options": {k: v for k, v in dataclasses.asdict(options).items() if k != "folds"}}
    fmt = {"dataset": results_key(out, dataset), "name": name}
    for path in sorted(p for d in (RUN_SCORES_DIR, RUN_FAILED_DIR) for p in (Path(out) / d.format(**fmt)).glob("fold*.json")):
        rec = read_json(path)
        old = {"method": rec.get("method"), "config": rec.get("config"),
               "options": {k: v for k, v in rec.get("options", {}).items() if k != "folds"}}
        diff = _differences(old, new)
        if diff:
            more = f" and {len(diff) - 3} more" if len(diff) > 3 else ""
            return f"{path}: run {name!r} was made with other settings ({'; '.join(diff[:3])}{more})"
    return None


def retire_run(out: Path, dataset: Dataset, name: str) -> Path:
    """Move run ``name``'s scores, failure records and predictions for ``dataset`` out of the way (renames, so no
    fold of the old run stays beside the new one's); returns the folder they went to, to delete once the new run
    finished."""
    fmt = {"dataset": results_key(out, dataset), "name": name}
    trash = Path(out) / REPLACED_DIR.format(**fmt, pid=os.getpid())
    for kind, folder in (("scores", Path(out) / RUN_SCORES_DIR.format(**fmt)),
                         ("failed", Path(out) / RUN_FAILED_DIR.format(**fmt)),
                         ("predictions", Path(out) / PREDICTIONS_DIR.format(**fmt))):
        if folder.exists():
            trash.mkdir(parents=True, exist_ok=True)
            os.replace(folder, trash / kind)
    return trash


def finished_fold(method_cls: MethodRef | type[Method], config, dataset: Dataset, fold: int, out: Path,
                  options: EvalOptions = EvalOptions()) -> dict | None:
    """The stored record of this fold if an earlier run had the same method, config, options, dataset
    content and commit and its predictions are all in place (``evaluate`` resumes with it), else None."""
    fmt = {"dataset": results_key(out, dataset), "name": options.name or method_cls.name, "fold": fold}
    path = Path(out) / SCORES_JSON.format(**fmt)
    if not path.is_file():
        return None
    record = read_json(path)
    want = _wanted_key(method_cls, config, dataset, options)
    pred_dir = Path(out) / PREDICTIONS_DIR.format(**fmt)
    frames = [(v, f) for v in record.get("test_videos", []) for f in select_test_frames(
        dataset.video(v).frame_ids, options.frame_stride, options.limit)]
    if want["commit"] is None or _resume_key(record) != want or \
            not all((pred_dir / PREDICTION_PNG.format(video_id=v, frame_id=f)).is_file() for v, f in frames):
        return None
    return record


def failed_fold(method_cls: MethodRef | type[Method], config, dataset: Dataset, fold: int, out: Path,
                options: EvalOptions = EvalOptions()) -> Path | None:
    """The failure record of this fold (``FAILED_JSON``: it passed a budget its config declares) if an earlier run
    had the same method, config, options, dataset content and commit, else None. ``evaluate`` does not run such a
    fold again: the same run would pass the same budget, and a larger budget is a new config."""
    fmt = {"dataset": results_key(out, dataset), "name": options.name or method_cls.name, "fold": fold}
    path = Path(out) / FAILED_JSON.format(**fmt)
    if not path.is_file():
        return None
    want = _wanted_key(method_cls, config, dataset, options)
    return path if want["commit"] is not None and _resume_key(read_json(path)) == want else None
