"""The `evaluate` command: a successful run, and input errors that name the culprit and exit 2."""
import numpy as np
import pytest

from selfseg.eval.cli import main
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


def test_cheating_method_is_stopped(analytic_dataset, tmp_path, capsys, monkeypatch):
    from selfseg.registry import METHODS

    monkeypatch.setitem(METHODS, "cheat-open", "test_protocol:CheatOpen")  # reads mask_inst in fit
    code, _, err = run_cli(capsys, "--method", "cheat-open", "--data", analytic_dataset, "--out", tmp_path, "--quiet")
    assert code == 2 and "tried to read ground truth" in err and "mask_inst" in err
    assert not (tmp_path / "scores").exists()
