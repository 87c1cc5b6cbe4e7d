"""Learned results are reproducible: the same commit, data, seed and settings give identical metrics and
instance maps on the same machine, whatever the environment's thread default (``OMP_NUM_THREADS``)."""
import json
from pathlib import Path

import pytest

from selfseg.eval.cli import main as evaluate

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def _run(tiny: Path, out: Path) -> tuple[dict, dict[str, bytes], list[float]]:
    """supervised, fold 0, 12 training steps, 2 test frames per video → (fold record, predictions, losses)."""
    assert evaluate(["--method", "supervised", "--data", str(tiny), "--config", str(CONFIGS / "supervised-tiny.yaml"),
                     "--set", "train.steps=12", "--folds", "0", "--limit", "2", "--out", str(out), "--quiet"]) == 0
    (record,) = (out / "scores").glob("*/supervised/fold0.json")
    preds = {str(p.relative_to(out / "predictions")): p.read_bytes() for p in (out / "predictions").rglob("*.png")}
    (log,) = (out / "work").rglob("training_log.json")
    return json.loads(record.read_text()), preds, json.loads(log.read_text())["loss"]


@pytest.mark.slow
def test_supervised_twice_gives_identical_results(tiny_dataset, tmp_path, monkeypatch):
    # the method process inherits the environment: different thread defaults must not change anything
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        monkeypatch.setenv(var, "1")
    first, first_preds, first_loss = _run(tiny_dataset, tmp_path / "a")
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        monkeypatch.setenv(var, "2")
    second, second_preds, second_loss = _run(tiny_dataset, tmp_path / "b")
    assert first_loss == second_loss
    assert first["metrics"] == second["metrics"]
    assert first["per_video"] == second["per_video"]
    assert len(first_preds) == first["metrics"]["n_frames"] > 0 and first_preds == second_preds
