"""CI regression on the real tiny preset: generate → evaluate (oracle, baselines, ours) through the CLIs.

The floors below sit well under the scores measured when they were set (see docs/demo.md's
leaderboard), so they catch breakage, not noise: a method falling to them is broken.
"""
import json
from pathlib import Path

import pytest

from selfseg.eval.cli import main as evaluate

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.fixture(scope="module")
def tiny(tiny_dataset) -> Path:
    """conftest's session-wide generated tiny preset."""
    return tiny_dataset


def scores(results: Path, name: str, fold: int) -> dict:
    return json.loads((results / "scores" / "tiny" / name / f"fold{fold}.json").read_text())["metrics"]


@pytest.mark.slow
def test_oracle_scores_one_on_tiny(tiny, tmp_path):
    assert evaluate(["--method", "oracle", "--data", str(tiny), "--out", str(tmp_path)]) == 0
    for fold in range(3):
        m = scores(tmp_path, "oracle", fold)
        assert m["n_frames"] > 0
        assert m["P"] == m["R"] == m["IoU"] == m["overlap_F"] == m["boundary_F"] == m["F75"] == 1.0


@pytest.mark.slow
def test_baselines_and_ours_on_tiny(tiny, tmp_path):
    out = str(tmp_path)
    for method in ("one-segment", "depth-clustering"):
        assert evaluate(["--method", method, "--data", str(tiny), "--out", out, "--folds", "0"]) == 0
    assert evaluate(["--method", "ours", "--data", str(tiny), "--out", out, "--folds", "0",
                     "--config", str(CONFIGS / "ours-tiny.yaml"),
                     "--set", "train.steps=60", "--set", "phi1_train.steps=60"]) == 0
    one, depth, ours = (scores(tmp_path, n, 0) for n in ("one-segment", "depth-clustering", "ours"))
    print({n: round(m["IoU"], 3) for n, m in (("one-segment", one), ("depth-clustering", depth), ("ours", ours))})
    assert depth["IoU"] > 0.6
    # measured (60 steps per network) on the pinned generator's tiny (manifest 1bcdf5c867ce3ff1): ours P .693 R .711
    # IoU .624, one-segment IoU .108. The earlier floor P > .7 was set on the pre-pinning scenes (P .899 then,
    # .814 at 9ffd189 on those scenes with this code and with db0526e's alike: the drop is the new scenes).
    assert ours["IoU"] > max(0.45, one["IoU"] + 0.2)
    assert ours["P"] > 0.55 and ours["R"] > 0.5
