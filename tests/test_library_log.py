"""Library output: Open3D's warnings go to the run's library log, counted in one line, never to the terminal."""
import concurrent.futures as cf
import os

import numpy as np

from selfseg.dataset import Dataset
from selfseg.eval.folds import EvalOptions
from selfseg.eval.layout import LIBRARY_LOG
from selfseg.eval.protocol import run_fold
from selfseg.library_log import LOG_ENV, run_log, summary
from selfseg.method.registration import register
from selfseg.method_api import Method

TOO_FEW = "Open3D WARNING 'Too few correspondences (N) after mutual filter, fall back to original correspondences.'"


def too_few_correspondences() -> tuple[np.ndarray, np.ndarray]:
    """A source of 300 scattered points and a target of 8: at most 8 mutual feature matches, under Open3D's 10 %
    of the source, so its RANSAC warns once per registration."""
    rng = np.random.default_rng(0)
    cube = np.array([[x, y, z] for x in (0, .02) for y in (0, .02) for z in (0, .02)], float)
    return rng.uniform(0, 0.06, (300, 3)), cube + rng.normal(0, 1e-3, cube.shape)


def test_a_registration_warning_goes_to_the_log_not_to_stdout(tmp_path, capfd):
    src, tgt = too_few_correspondences()
    register(src, tgt)  # outside a run: Open3D prints as it always did
    assert "Too few correspondences" in capfd.readouterr().out
    print("before", flush=True)
    with run_log(tmp_path / "library.log") as log:
        assert os.environ[LOG_ENV] == str(log)
        register(src, tgt)
        print("python's own output stays", flush=True)
    assert LOG_ENV not in os.environ
    assert capfd.readouterr() == ("before\npython's own output stays\n", "")
    assert summary(log) == f"library log {log}: 1 × {TOO_FEW}"


def _register_too_few(_):
    return register(*too_few_correspondences()).fitness


def test_worker_processes_write_to_the_same_log(tmp_path, capfd):
    with run_log(tmp_path / "library.log") as log:
        with cf.ProcessPoolExecutor(2) as ex:  # started inside the run, as pruning's registration pool is
            list(ex.map(_register_too_few, range(3)))
    assert capfd.readouterr().out == ""
    assert summary(log) == f"library log {log}: 3 × {TOO_FEW}"
    assert summary(tmp_path / "missing.log") is None
    (tmp_path / "empty.log").write_text("")
    assert summary(tmp_path / "empty.log") is None


class Registering(Method):
    """Registers two clouds that make Open3D warn, in fit; one segment per frame."""

    name = "registering"

    def fit(self, train_videos):
        register(*too_few_correspondences())
        register(*too_few_correspondences())

    def segment(self, video, frame_id, fg_mask):
        return fg_mask.astype(np.uint16)


def test_evaluate_counts_a_folds_warnings_in_one_line(analytic_dataset, tmp_path, capfd):
    ds = Dataset(analytic_dataset)
    run_fold(Registering, None, ds, 0, tmp_path, EvalOptions(frame_stride=2, n_boot=100), progress=False)
    log = tmp_path / LIBRARY_LOG.format(name="registering", dataset=ds.name, fold=0)
    out, err = capfd.readouterr()
    assert "Too few" not in out + err.replace(TOO_FEW, "")
    assert err.strip().splitlines() == [f"registering fold 0: library log {log}: 2 × {TOO_FEW}"]
