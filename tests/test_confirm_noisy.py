"""scripts/confirm_noisy.sh: the noisy rows run only from a checkout of the freeze, only for presets with a
noisy variant (one line, exit 2, nothing run)."""
import os
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


def test_a_seed_that_is_not_the_freezes_is_refused_before_anything_runs(tmp_path):
    """SEEDS restricts the run to some of the freeze's seeds; any other seed is refused in one line, exit 2."""
    r = subprocess.run(["bash", str(SCRIPT), str(ROOT), str(tmp_path / "runs"), "calibrated"], capture_output=True,
                       text=True, timeout=120, env={**os.environ, "SEEDS": "963040 123456"})
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert r.stderr.startswith("scripts/confirm_noisy.sh: seed 123456 is not one of the freeze's: 963040 487063 247166")
    assert list((tmp_path / "runs").iterdir()) == []


RESUME = ROOT / "scripts" / "confirm_resume.sh"


def _status() -> str:
    """This checkout's git status, untracked files included."""
    return subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=all"],
                          capture_output=True, text=True, check=True).stdout


def test_resume_restores_the_archive_and_runs_nothing_from_a_checkout_that_is_not_the_freeze(tmp_path):
    """scripts/confirm_resume.sh with this checkout as the clone: the first calibrated freeze's archived fold
    records come back into RUNS, then the freeze check refuses the checkout (its code moved) and nothing starts."""
    before = _status()
    r = subprocess.run(["bash", str(RESUME), "calibrated", "calibrated", str(ROOT), str(tmp_path / "runs")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "that is a new freeze" in r.stderr
    archived = ROOT / "leaderboards/results/calibrated-confirm"
    for seed in sorted(archived.glob("seed-*")):
        want = sorted(p.relative_to(archived) for p in seed.glob("results/scores/*/*/fold*.json"))
        got = sorted(p.relative_to(tmp_path / "runs") for p in (tmp_path / "runs" / seed.name).rglob("fold*.json"))
        assert want and got == want
    assert not (tmp_path / "runs" / "confirm.log").exists()  # nothing was started
    assert _status() == before  # nothing written into the clone (a frozen checkout must stay clean)
    r = subprocess.run(["bash", str(RESUME), "calibrated", "calibrated-9", str(tmp_path / "c"), str(tmp_path / "r")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "calibrated-9-freeze.json: no such freeze record" in r.stderr
    assert not (tmp_path / "c").exists()
