import os
import shutil
import signal
import sys
from pathlib import Path

import pytest

from selfseg.analytic import make_dataset, two_box_scenes


@pytest.fixture(scope="session")
def analytic_dataset(tmp_path_factory) -> Path:
    """Three ray-cast videos of boxes and a cylinder (6 frames, 160×120), in the real format.

    ``SELFSEG_ANALYTIC_DATASET``: a copy made earlier by this fixture, for a machine without open3d (the ray caster),
    such as a lent GPU machine (bench/gpu_checks.sh)."""
    prebuilt = os.environ.get("SELFSEG_ANALYTIC_DATASET")
    if prebuilt:
        return shutil.copytree(prebuilt, tmp_path_factory.mktemp("analytic") / "data")
    return make_dataset(tmp_path_factory.mktemp("analytic"), two_box_scenes())


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """The tiny preset with Workbench images (ground truth identical to Cycles'), generated once per
    test run by the ``generate_scenes`` command (so with its pinned numerical libraries, as users get it)
    and shared by every module that needs real generated scenes. Under pytest-xdist the workers share one
    copy: the first generates it under a lock, the others wait and find it finished (the command resumes)."""
    import subprocess

    from selfseg.fileio import exclusive_lock

    base = tmp_path_factory.getbasetemp()
    run_dir = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base  # xdist: the run's, above the workers'
    out = run_dir / "tiny-workbench" / "data"
    cmd = [sys.executable, "-m", "selfseg.generate.cli", "--preset", "tiny", "--renderer", "workbench", "--out",
           str(out), "--workers", "2", "--quiet"]
    with exclusive_lock(run_dir / "tiny-workbench.lock", "the test run's tiny dataset", wait=True):
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=1200)
    assert run.returncode == 0, run.stderr
    return out


def _sigint_default() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture
def ctrl_c_child() -> dict:
    """Popen keyword arguments for a child that a test interrupts like a terminal's Ctrl-C: its own process
    group, and SIGINT at its default even when the suite runs as a background job (which ignores SIGINT,
    and Python keeps an ignored SIGINT ignored)."""
    return {"start_new_session": True, "preexec_fn": _sigint_default}
