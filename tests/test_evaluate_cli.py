"""The `evaluate` command: a successful run, input errors that name the culprit and exit 2, and a fold over its
budget."""
import dataclasses
import os

import numpy as np
import pytest

from selfseg.dataset import Dataset
from selfseg.eval.cli import main
from selfseg.eval.folds import fold_split
from selfseg.eval.layout import FAILED_JSON, FOLD_LOCK, PREDICTIONS_DIR
from selfseg.eval.leaderboard import main as build_leaderboards
from selfseg.eval.protocol import EXIT_OVER_BUDGET
from selfseg.fileio import exclusive_lock
from selfseg.method_api import BudgetExceededError, Method
from selfseg.writers import write_inst


def run_cli(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_run_prints_table_and_writes_results(analytic_dataset, tmp_path, capsys):
    code, out, err = run_cli(capsys, "--method", "fg-components", "--data", analytic_dataset, "--folds", "0,2",
                             "--frame-stride", "3", "--limit", "1", "--out", tmp_path, "--quiet")
    assert code == 0, err
    assert "mean±std" in out and "95% CI" in out and "IoU" in out
    assert sorted(p.name for p in (tmp_path / "scores/analytic/fg-components").glob("*.json")) == \
        ["fold0.json", "fold2.json"]


def test_list_methods(capsys):
    code, out, _ = run_cli(capsys, "--list-methods")
    assert code == 0
    for name in ("oracle", "one-segment", "fg-components", "depth-clustering", "external"):
        assert name in out


def test_unknown_method_suggests(analytic_dataset, tmp_path, capsys):
    code, _, err = run_cli(capsys, "--method", "depth-clusterin", "--data", analytic_dataset, "--out", tmp_path)
    assert code == 2 and "depth-clustering" in err and "Traceback" not in err


def test_missing_dataset(tmp_path, capsys):
    code, _, err = run_cli(capsys, "--method", "oracle", "--data", tmp_path / "nope", "--out", tmp_path)
    assert code == 2 and str(tmp_path / "nope") in err


def test_bad_config_key(analytic_dataset, tmp_path, capsys):
    code, _, err = run_cli(capsys, "--method", "depth-clustering", "--data", analytic_dataset,
                           "--set", "distance=0.02", "--out", tmp_path)
    assert code == 2 and "distance_m" in err


@pytest.fixture
def predictions(analytic_dataset, tmp_path):
    """A complete external predictions folder for stride 3 (frames 0 and 3 of each video)."""
    root = tmp_path / "preds"
    for vid in ("000000", "000001", "000002"):
        for f in (0, 3):
            write_inst(root / vid / f"{f:06d}.png", np.ones((120, 160), np.uint16))
    return root


def external(capsys, data, preds, out):
    return run_cli(capsys, "--method", "external", "--predictions", preds, "--data", data, "--frame-stride", "3",
                   "--out", out, "--quiet", "--name", "uois")


def test_external_predictions_ok(analytic_dataset, predictions, tmp_path, capsys):
    code, out, err = external(capsys, analytic_dataset, predictions, tmp_path / "out")
    assert code == 0, err
    assert (tmp_path / "out/scores/analytic/uois/fold0.json").is_file()


def test_external_missing_frame(analytic_dataset, predictions, tmp_path, capsys):
    (predictions / "000001" / "000003.png").unlink()
    code, _, err = external(capsys, analytic_dataset, predictions, tmp_path / "out")
    assert code == 2 and str(predictions / "000001" / "000003.png") in err and "missing" in err


def test_external_wrong_size(analytic_dataset, predictions, tmp_path, capsys):
    write_inst(predictions / "000002" / "000000.png", np.ones((60, 80), np.uint16))
    code, _, err = external(capsys, analytic_dataset, predictions, tmp_path / "out")
    assert code == 2 and str(predictions / "000002" / "000000.png") in err and "80×60" in err


def test_external_missing_folder(analytic_dataset, tmp_path, capsys):
    code, _, err = external(capsys, analytic_dataset, tmp_path / "nothing", tmp_path / "out")
    assert code == 2 and str(tmp_path / "nothing") in err


def test_predictions_flag_needs_external(analytic_dataset, tmp_path, capsys):
    code, _, err = run_cli(capsys, "--method", "oracle", "--predictions", tmp_path, "--data", analytic_dataset)
    assert code == 2 and "--predictions" in err


def test_cheating_method_is_stopped(analytic_dataset, tmp_path, capsys):
    # a user's method (tests/ is on sys.path: pytest puts it there) that reads mask_inst in fit; the registry is read
    # in the method's own process, so a name patched into this process's registry would not reach it
    code, _, err = run_cli(capsys, "--method", "test_protocol:CheatOpen", "--data", analytic_dataset, "--out", tmp_path,
                           "--quiet")
    assert code == 2 and "tried to read ground truth" in err and "mask_inst" in err
    assert not (tmp_path / "scores").exists()


def test_rerun_with_other_settings_refuses_or_replaces(analytic_dataset, tmp_path, capsys):
    """A run name holds one run: the same name with another config is refused in one line naming the difference
    (nothing changes), and with --replace the old folds and predictions are all replaced, none left beside."""
    import json

    base = ["--method", "depth-clustering", "--data", analytic_dataset, "--frame-stride", "3", "--out", tmp_path,
            "--quiet"]
    scores = tmp_path / "scores/analytic/depth-clustering"
    preds = tmp_path / "predictions/depth-clustering/analytic"
    assert run_cli(capsys, *base, "--folds", "0,1", "--set", "distance_m=0.01")[0] == 0
    before = {p.name: p.read_bytes() for p in scores.iterdir()}
    frames_before = sorted(p.relative_to(preds) for p in preds.rglob("*.png"))

    code, _, err = run_cli(capsys, *base, "--folds", "0", "--set", "distance_m=0.03")
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "distance_m 0.01 → 0.03" in err and str(scores / "fold0.json") in err and "--replace" in err
    assert {p.name: p.read_bytes() for p in scores.iterdir()} == before
    # the same settings again are no conflict: the finished folds are reused
    assert run_cli(capsys, *base, "--folds", "0,1", "--set", "distance_m=0.01")[0] == 0
    assert {p.name: p.read_bytes() for p in scores.iterdir()} == before

    code, _, err = run_cli(capsys, *base, "--folds", "2", "--set", "distance_m=0.03", "--replace")
    assert code == 0, err
    assert sorted(p.name for p in scores.glob("*.json")) == ["fold2.json"]  # folds 0 and 1 of the old run are gone
    assert json.loads((scores / "fold2.json").read_text())["config"]["distance_m"] == 0.03
    frames_after = sorted(p.relative_to(preds) for p in preds.rglob("*.png"))
    assert frames_after and set(frames_after).isdisjoint(frames_before)  # only fold 2's video remains
    assert not any((tmp_path / "replaced").rglob("*.json"))


def test_a_fold_another_process_runs_is_refused_untouched(analytic_dataset, tmp_path, capsys):
    """While another process holds fold 0 of a run, evaluate of that fold exits 2 naming the fold and the holder and
    leaves the other's predictions alone; fold 1 of the same run goes ahead, and fold 0 runs once it is free."""
    args = ["--method", "fg-components", "--data", analytic_dataset, "--frame-stride", "3", "--limit", "1", "--out",
            tmp_path, "--quiet"]
    assert run_cli(capsys, *args, "--folds", "0")[0] == 0
    fmt = {"dataset": "analytic", "name": "fg-components", "fold": 0}
    preds = sorted((tmp_path / PREDICTIONS_DIR.format(**fmt)).rglob("*.png"))
    (tmp_path / "scores/analytic/fg-components/fold0.json").unlink()  # not finished: evaluate would rerun it
    with exclusive_lock(tmp_path / FOLD_LOCK.format(**fmt), "held by the test"):
        code, _, err = run_cli(capsys, *args, "--folds", "0")
        assert code == 2 and "fold 0 of run 'fg-components'" in err and f"process {os.getpid()}" in err, err
        assert sorted((tmp_path / PREDICTIONS_DIR.format(**fmt)).rglob("*.png")) == preds and preds
        assert run_cli(capsys, *args, "--folds", "1")[0] == 0
    code, _, err = run_cli(capsys, *args, "--folds", "0")
    assert code == 0 and (tmp_path / "scores/analytic/fg-components/fold0.json").is_file(), err


@dataclasses.dataclass
class OverBudgetConfig:
    over_budget: bool = True  # fit passes its budget when video 000001 is not among its training videos


class OverBudgetWithout(Method):
    """The whole foreground as one segment, but (``over_budget``) passes its budget when video 000001 is not a
    training video (one fold of the analytic dataset)."""

    name = "over-budget"
    config_cls = OverBudgetConfig

    def fit(self, train_videos):
        if self.config.over_budget and "000001" not in [v.video_id for v in train_videos]:
            raise BudgetExceededError("used more than its CPU budget of 1 s")

    def segment(self, video, frame_id, fg_mask):
        return fg_mask.astype(np.uint16)


def test_a_fold_over_its_budget_is_recorded_failed_and_not_run_again(analytic_dataset, tmp_path, capsys):
    """A fold whose method passes its budget gets a failure record (not scored), the other folds run, the exit status
    is 3; run again, the failed fold is not retried (the same run would fail again), and --replace retires it."""
    import json

    args = ["--method", "test_evaluate_cli:OverBudgetWithout", "--data", analytic_dataset, "--frame-stride", "3",
            "--out", tmp_path, "--quiet"]
    k = next(f for f in range(3) if "000001" in fold_split(Dataset(analytic_dataset), f)[1])  # the fold to fail
    failed = tmp_path / FAILED_JSON.format(dataset="analytic", name="over-budget", fold=k)
    scores = tmp_path / "scores/analytic/over-budget"
    code, out, err = run_cli(capsys, *args)
    assert code == EXIT_OVER_BUDGET, err
    assert sorted(p.name for p in scores.glob("*.json")) == [f"fold{f}.json" for f in range(3) if f != k]
    assert "IoU" in out
    rec = json.loads(failed.read_text())
    assert rec["fold"] == k and rec["failure"]["kind"] == "budget" and "CPU budget of 1 s" in rec["failure"]["message"]
    assert rec["config_hash"] and rec["git"]["commit"] and "metrics" not in rec
    assert f"fold {k}" in err and str(failed) in err
    assert build_leaderboards(["--results", str(tmp_path), "--out", str(tmp_path / "lb")]) == 0  # names the failure
    assert f"- over-budget (2d), fold {k}: used more than its CPU budget of 1 s" in (tmp_path / "lb/analytic.md").read_text()

    code, _, err = run_cli(capsys, *args, "--folds", str(k))
    assert code == EXIT_OVER_BUDGET and "earlier identical run; not run again" in err
    # a failure record of another commit is not this run's: the fold runs (and fails) again, rewriting it
    rec["git"]["commit"] = "0" * 40
    failed.write_text(json.dumps(rec))
    code, _, err = run_cli(capsys, *args, "--folds", str(k))
    assert code == EXIT_OVER_BUDGET and "CPU budget of 1 s" in err
    assert json.loads(failed.read_text())["git"]["commit"] != "0" * 40
    # --replace with another config retires the old run, its failure record too
    code, _, err = run_cli(capsys, *args, "--folds", str(k), "--set", "over_budget=false", "--replace")
    assert code == 0, err
    assert not failed.exists() and sorted(p.name for p in scores.glob("*.json")) == [f"fold{k}.json"]
