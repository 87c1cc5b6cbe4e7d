"""A user's own method, outside the registry: ``evaluate --method package.module:ClassName`` imports it from
PYTHONPATH only in the method's own sandboxed process, on the same unlabeled view as the built-in methods;
name, module and class errors found there come back as one line, exit code 2."""
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from selfseg.eval.cli import main as evaluate

USER_PACKAGE = {
    "__init__.py": "",
    "seg.py": '''
        """A user's method: the whole foreground as one segment; records where fit ran."""
        import multiprocessing
        from dataclasses import dataclass

        import numpy as np

        from selfseg.method_api import Method


        @dataclass
        class OneLabelConfig:
            label: int = 7


        class OneLabel(Method):
            """Every foreground pixel gets config.label."""

            name = "my-one-label"
            config_cls = OneLabelConfig
            needs_fit = True

            def fit(self, train_videos):
                self.workdir.mkdir(parents=True, exist_ok=True)
                (self.workdir / "fit.json").write_text(
                    '{"process": "%s", "root": "%s"}' % (multiprocessing.current_process().name, train_videos[0].root))

            def segment(self, video, frame_id, fg_mask):
                return np.where(fg_mask, self.config.label, 0).astype(np.uint16)


        class Unnamed(Method):
            def segment(self, video, frame_id, fg_mask):
                return fg_mask.astype(np.uint16)


        class NamedLikeOracle(Unnamed):
            name = "oracle"
    ''',
    "cheat.py": '''
        """Reads a ground-truth mask while its module is imported (the path from CHEAT_ROOT)."""
        import os

        from selfseg.dataset import MASK_INST
        from selfseg.guard import GroundTruthAccessError
        from selfseg.method_api import Method

        try:
            COPIED = open(os.path.join(os.environ["CHEAT_ROOT"], MASK_INST.format(video_id="000000", frame_id=0)),
                          "rb").read()
        except GroundTruthAccessError:
            COPIED = None


        class ImportCheat(Method):
            name = "my-import-cheat"

            def segment(self, video, frame_id, fg_mask):
                return fg_mask.astype("uint16")
    ''',
    "broken.py": "def oops(:\n",
    "spoof.py": '''
        """Takes a registered name, after removing it from the registry of the process that imports it."""
        import selfseg.registry
        from selfseg.method_api import Method

        selfseg.registry.METHODS.pop("oracle")


        class Spoof(Method):
            name = "oracle"

            def segment(self, video, frame_id, fg_mask):
                return fg_mask.astype("uint16")
    ''',
}


@pytest.fixture
def user_path(tmp_path) -> Path:
    """A folder holding the package ``mymethods`` (not importable until put on PYTHONPATH)."""
    root = tmp_path / "userpath"
    for name, text in USER_PACKAGE.items():
        (root / "mymethods").mkdir(parents=True, exist_ok=True)
        (root / "mymethods" / name).write_text(textwrap.dedent(text))
    yield root
    for name in [m for m in sys.modules if m.split(".")[0] == "mymethods"]:  # imported by in-process tests
        del sys.modules[name]


def _evaluate_process(user_path: Path, *argv, **env) -> subprocess.CompletedProcess:
    """``evaluate`` as a user runs it: a fresh interpreter with the user's folder on PYTHONPATH."""
    environment = {**os.environ, "PYTHONPATH": str(user_path), **env}
    return subprocess.run([sys.executable, "-m", "selfseg.eval.cli", *map(str, argv)], capture_output=True,
                          text=True, env=environment, timeout=300)


def test_user_method_runs_isolated_and_is_scored(analytic_dataset, user_path, tmp_path):
    out = tmp_path / "out"
    done = _evaluate_process(user_path, "--method", "mymethods.seg:OneLabel", "--data", analytic_dataset,
                             "--folds", "0", "--frame-stride", "3", "--set", "label=3", "--out", out, "--quiet")
    assert done.returncode == 0, done.stderr
    (record,) = (out / "scores").glob("*/my-one-label/fold0.json")
    record = json.loads(record.read_text())
    assert record["method"] == "my-one-label" and record["config"] == {"label": 3}
    assert record["isolation"] == "sandbox" and record["ground_truth"] == "none"
    assert record["metrics"]["n_frames"] > 0 and 0 < record["metrics"]["IoU"] <= 1
    (fit,) = (out / "work").rglob("fit.json")
    fit = json.loads(fit.read_text())
    # fit ran in the method's own process, on the unlabeled view, never on the real dataset
    assert fit["process"] == "selfseg-my-one-label"
    assert "_views" in fit["root"] and not fit["root"].startswith(str(analytic_dataset))
    preds = list((out / "predictions" / "my-one-label").rglob("*.png"))
    assert len(preds) == record["metrics"]["n_frames"]


def test_user_method_reading_ground_truth_at_import_is_stopped(analytic_dataset, user_path, tmp_path):
    out = tmp_path / "out"
    done = _evaluate_process(user_path, "--method", "mymethods.cheat:ImportCheat", "--data", analytic_dataset,
                             "--folds", "0", "--out", out, "--quiet", CHEAT_ROOT=str(analytic_dataset))
    assert done.returncode == 2 and "tried to read ground truth" in done.stderr and "mask_inst" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    assert not (out / "scores").exists()


@pytest.mark.parametrize("spec, message", [
    ("nosuch_module_xyz:Thing", "cannot import module 'nosuch_module_xyz'"),
    ("mymethods.seg:Missing", "has no 'Missing'"),
    ("mymethods.seg:OneLabelConfig", "not a subclass of selfseg.method_api.Method"),
    ("mymethods.seg:Unnamed", "set the class attribute name"),
    ("mymethods.seg:NamedLikeOracle", "is a registered method's"),
    ("mymethods.spoof:Spoof", "is a registered method's"),  # checked here, not in the method's process
    ("mymethods.broken:X", "broken.py:1"),
    ("mymethods.seg:", "expected a registered name or 'package.module:ClassName'"),
])
def test_bad_spec_is_one_line_exit_2(analytic_dataset, user_path, tmp_path, capsys, monkeypatch, spec, message):
    monkeypatch.syspath_prepend(str(user_path))
    code = evaluate(["--method", spec, "--data", str(analytic_dataset), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
