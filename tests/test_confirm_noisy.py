"""scripts/confirm_noisy.sh: the noisy rows run only from a checkout of the freeze, only for presets with a
noisy variant (one line, exit 2, nothing run)."""
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "confirm_noisy.sh"


def _run(*args):
    return subprocess.run(["bash", str(SCRIPT), *map(str, args)], capture_output=True, text=True, timeout=120)


def test_a_preset_without_a_noisy_variant_is_refused(tmp_path):
    r = _run(ROOT, tmp_path / "runs", "benchmark")
    assert r.returncode == 2 and r.stderr.strip() == "scripts/confirm_noisy.sh: no noisy variant of preset 'benchmark'"
    assert list((tmp_path / "runs").iterdir()) == []


def test_a_checkout_that_is_not_the_freeze_runs_nothing(tmp_path):
    """This checkout's code has moved since calibrated's freeze: `confirm check` refuses it before any seed."""
    r = _run(ROOT, tmp_path / "runs", "calibrated")
    assert r.returncode == 2 and "that is a new freeze" in r.stderr and "seed" not in r.stdout
    assert list((tmp_path / "runs").iterdir()) == []
    assert _run(ROOT).returncode == 2  # usage
