"""bench/profile_run.py on a resumed run folder: the total names only the last invocation, the step sum all of them."""
import json
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "bench"


def test_a_resumed_run_reports_its_last_invocation_and_the_sum_of_every_step(tmp_path):
    run = tmp_path / "run"
    (run / "results" / "work").mkdir(parents=True)
    # a first invocation ran generation and V2, the resumed one skipped generation (4 s) and ran `ours`
    (run / "timings.tsv").write_text("generate\t883\t945\t1047\nours-v2\t4659\t3\t144\n"
                                     "generate\t4\t3\t193\nours\t2654\t2\t110\ntotal\t2660\n")
    out = tmp_path / "profile.json"
    r = subprocess.run([sys.executable, str(BENCH / "profile_run.py"), str(run), "--out", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    got = json.loads(out.read_text())
    assert got["total_wall_s"] == 2660 and got["steps_wall_sum_s"] == 883 + 4659 + 4 + 2654
    assert [s["step"] for s in got["steps"]] == ["generate", "ours-v2", "generate", "ours"]
    assert "sum of step walls 8200 s" in r.stdout


def test_a_folder_without_timings_is_refused_in_one_line(tmp_path):
    r = subprocess.run([sys.executable, str(BENCH / "profile_run.py"), str(tmp_path), "--out", str(tmp_path / "p.json")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "timings.tsv: missing" in r.stderr
