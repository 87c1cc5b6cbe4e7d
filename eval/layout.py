"""The results folder: its layout (every path template under ``OUT``), the schema version of its records, and the
key a dataset's results are filed under. Output layout under ``OUT`` (default ``results/``)::

    scores/<dataset>/<name>/fold<k>.json          result record (SCHEMA_VERSION; fields: :mod:`selfseg.eval.protocol`)
    scores/<dataset>/<name>/fold<k>.frames.jsonl  one line of metrics per test frame
    predictions/<name>/<dataset>/<video_id>/<frame_id:06d>.png   uint16 instance maps
    work/<name>/<dataset>/fold<k>/                the method's cache (``Method.workdir``)
    work/<name>/<dataset>/fold<k>/library.log     what libraries (Open3D) printed while the fold's method ran
    work/_views/<content hash>-<poses>/<folder>/  the unlabeled copy of the dataset that methods see
    work/_stages/<content hash>-<poses>/          label-free registered methods' per-video stage caches (``Method.stage_root``)
    work/<name>/<dataset>/fold<k>/_stages/        the stage cache of a registered method given labels (its fold's own)
    rejected/<dataset>/<name>/fold<k>.json        a fold whose method reached for ground truth (not scored)
    failed/<dataset>/<name>/fold<k>.json          a fold whose method passed a compute budget its config declares
                                                  (not scored, not run again: :mod:`selfseg.eval.resume`)
    replaced/<dataset>/<name>.<pid>/              ``evaluate --replace``: the old run, until the new one finished

``<name>`` is the method name unless ``--name`` gives a variant name; ``<dataset>`` is the dataset's name,
or ``<name>-<content hash>`` when results of another dataset of that name are already there
(:func:`results_key`), so two datasets never mix. Each video is a test video in exactly one fold, so
``predictions/<name>/<dataset>/`` is a valid folder for the ``external`` method (re-scoring never re-runs a
method).

This module is the results folder's public face: baselines and the leaderboard code import it, never the
protocol's internals.
"""
from __future__ import annotations

from pathlib import Path

from selfseg.dataset import Dataset
from selfseg.fileio import read_json

SCHEMA_VERSION = 1
N_FOLDS = 3
SCORES_DIR = "scores"
RUN_SCORES_DIR = SCORES_DIR + "/{dataset}/{name}"  # one run's folds
SCORES_JSON = RUN_SCORES_DIR + "/fold{fold}.json"
FRAMES_JSONL = RUN_SCORES_DIR + "/fold{fold}.frames.jsonl"
PREDICTIONS_DIR = "predictions/{name}/{dataset}"
PREDICTION_PNG = "{video_id}/{frame_id:06d}.png"  # one frame's instance map in PREDICTIONS_DIR (and in `external`'s input)
WORK_DIR = "work/{name}/{dataset}/fold{fold}"
LIBRARY_LOG = WORK_DIR + "/library.log"  # a fold's library messages (selfseg.library_log), rewritten by each run
STAGES_DIR = "work/_stages"  # per-video stage caches shared by every run and fold in OUT (evaluate3d's stage_root)
STAGE_ROOT_DIR = "work/_stages/{content_hash}-{poses}"  # label-free registered methods' stage_root under evaluate
LABELED_STAGE_ROOT_DIR = WORK_DIR + "/_stages"  # the stage_root of a registered method given labels: its fold's own
METHOD_OUTPUT_DIR = "predictions/{name}/.{dataset}.fold{fold}.method"  # where the method's process writes predictions
REJECTED_DIR = "rejected"
REJECTED_JSON = REJECTED_DIR + "/{dataset}/{name}/fold{fold}.json"  # a fold whose method reached for ground truth
FAILED_DIR = "failed"
RUN_FAILED_DIR = FAILED_DIR + "/{dataset}/{name}"  # one run's folds that failed under a budget (BudgetExceededError)
FAILED_JSON = RUN_FAILED_DIR + "/fold{fold}.json"
FOLD_LOCK = "work/{name}/{dataset}/.fold{fold}.lock"  # held while a process runs this fold (fileio.exclusive_lock)
VIEW_DIR = "work/_views/{content_hash}-{poses}/{folder}"  # the unlabeled copy of a dataset that methods see
REPLACED_DIR = "replaced/{dataset}/{name}.{pid}"  # evaluate --replace: the old run, deleted once the new one finished


def results_key(out: Path, dataset: Dataset) -> str:
    """The folder name a dataset's results are filed under in ``out``: its name, or ``<name>-<content hash>``
    when ``scores/<name>/`` already holds results of a different dataset with the same name."""
    content = dataset.content_hash()
    for path in sorted((Path(out) / SCORES_DIR / dataset.name).glob("*/fold*.json")):
        if read_json(path).get("dataset", {}).get("content_hash") != content:
            return f"{dataset.name}-{content[:8]}"
    return dataset.name
