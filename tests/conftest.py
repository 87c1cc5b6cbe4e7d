import signal
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))  # tests/analytic.py

from analytic import make_dataset, two_box_scenes  # noqa: E402


@pytest.fixture(scope="session")
def analytic_dataset(tmp_path_factory) -> Path:
    """Three ray-cast videos of boxes and a cylinder (6 frames, 160×120), in the real format."""
    return make_dataset(tmp_path_factory.mktemp("analytic"), two_box_scenes())


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """The tiny preset with Workbench images (ground truth identical to Cycles'), generated once per
    test session and shared by every module that needs real generated scenes."""
    from selfseg.generate.cli import main as generate_scenes

    out = tmp_path_factory.getbasetemp() / "tiny-workbench" / "data"
    assert generate_scenes(["--preset", "tiny", "--renderer", "workbench", "--out", str(out), "--quiet"]) == 0
    return out


def _sigint_default() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture
def ctrl_c_child() -> dict:
    """Popen keyword arguments for a child that a test interrupts like a terminal's Ctrl-C: its own process
    group, and SIGINT at its default even when the suite runs as a background job (which ignores SIGINT,
    and Python keeps an ignored SIGINT ignored)."""
    return {"start_new_session": True, "preexec_fn": _sigint_default}
