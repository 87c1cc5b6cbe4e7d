"""scripts/queue.sh (the job queue of scripts/benchmark.sh), run by bash on small jobs that log their start and end."""
import subprocess
from pathlib import Path

QUEUE = Path(__file__).resolve().parents[1] / "scripts" / "queue.sh"


def run_queue(tmp_path, jobs: dict[str, str], specs: list[str], slots: int = 2,
              out: list[str] | None = None) -> tuple[int, list[tuple[str, str]]]:
    """Run the queue on jobs {name: shell body}; each job appends 'start NAME' and 'end NAME' to a trace
    around its body. Returns the exit code and the trace as (event, name) pairs in order; the queue's own
    stdout lines go to `out` when given."""
    trace = tmp_path / "trace"
    funcs = "".join(f'job_{n}() {{ echo "start {n}" >> {trace}; {body}; local rc=$?; echo "end {n}" >> {trace}; '
                    f"return $rc; }}\n" for n, body in jobs.items())
    script = f"set -euo pipefail\n. {QUEUE}\n{funcs}run_queue {slots} {tmp_path}/logs {' '.join(specs)}\n"
    proc = subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=60)
    rc = proc.returncode
    if out is not None:
        out.extend(proc.stdout.splitlines())
    events = [tuple(line.split()) for line in trace.read_text().splitlines()] if trace.exists() else []
    return rc, events


def test_jobs_wait_for_their_dependencies_and_fill_both_slots(tmp_path):
    jobs = {"phi": "sleep 0.3", "long": "sleep 2.0", "a": "sleep 0.2", "b": "sleep 0.2", "c": "sleep 0.1"}
    out: list[str] = []
    rc, ev = run_queue(tmp_path, jobs, ["phi", "long", "a:phi", "b:phi", "c"], out=out)
    assert rc == 0 and sorted(ev) == sorted([(e, n) for n in jobs for e in ("start", "end")])
    # the first two side by side (started in order, but two forked jobs may log their starts either way round)
    assert sorted(ev[:2]) == [("start", "long"), ("start", "phi")]
    assert [line.split()[1] for line in out if " started " in line][:2] == ["phi", "long"]  # the queue's order
    at = {e: i for i, e in enumerate(ev)}
    for n in ("a", "b"):
        assert at[("start", n)] > at[("end", "phi")]  # after its dependency
    # the free slot takes the ready jobs in the given order while long still runs
    assert at[("start", "a")] < at[("start", "b")] < at[("start", "c")] < at[("end", "long")]
    running = 0
    for e, _ in ev:
        running += 1 if e == "start" else -1
        assert running <= 2


def test_a_failure_starts_nothing_new_and_fails_the_queue(tmp_path):
    jobs = {"bad": "sleep 0.1; false", "slow": "sleep 0.5", "after": "true", "needs_bad": "true"}
    rc, ev = run_queue(tmp_path, jobs, ["bad", "slow", "after", "needs_bad:bad"])
    assert rc == 1
    assert ("end", "slow") in ev  # the running job finished
    assert ("start", "after") not in ev and ("start", "needs_bad") not in ev
    assert (tmp_path / "logs" / "bad.log").is_file()


def test_unknown_dependency_or_job_is_refused_before_anything_runs(tmp_path):
    rc, ev = run_queue(tmp_path, {"a": "true"}, ["a:nothere"])
    assert rc == 2 and ev == []
    rc, ev = run_queue(tmp_path, {"a": "true"}, ["a", "b"])
    assert rc == 2 and ev == []
