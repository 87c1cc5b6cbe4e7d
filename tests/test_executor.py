"""Executors on real Ray: same results as local pools, a killed worker retried, bad options refused.

Ray clusters here bind the loopback interface only (RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0) and are
stopped by killing the process group each test started.
"""
from __future__ import annotations

import filecmp
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")  # read by Ray when imported

from selfseg.eval.cli import main as evaluate  # noqa: E402
from selfseg.executor import ExecutorError, check_shared_folder, make_executor  # noqa: E402
from selfseg.fileio import read_json  # noqa: E402
from selfseg.generate.cli import main as generate_scenes  # noqa: E402
from selfseg.generate.determinism import pinned_vars  # noqa: E402
from selfseg.method.matching import MatchConfig, SceneGraph, match_all  # noqa: E402
from selfseg.method.pruning import PruneConfig, register_clouds  # noqa: E402

RAY = str(Path(sys.executable).parent / "ray")
TINY = ["--preset", "tiny", "--renderer", "workbench", "--quiet"]
# generate_scenes as conftest's tiny_dataset runs it, in this process's environment: main(argv) does not pin itself
UNPINNED_COMMAND = [sys.executable, "-c", "import sys; from selfseg.generate.cli import main; sys.exit(main(sys.argv[1:]))"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _children(pid: int) -> list[int]:
    """Every descendant process of ``pid`` (from /proc)."""
    parent = {}
    for p in Path("/proc").iterdir():
        try:
            parent[int(p.name)] = int((p / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (ValueError, OSError, IndexError):
            continue
    out, todo = [], [pid]
    while todo:
        current = todo.pop()
        kids = [c for c, pp in parent.items() if pp == current]
        out += kids
        todo += kids
    return out


class Cluster:
    """`ray start --head --block` with 2 CPUs on 127.0.0.1, optionally behind a command prefix (a namespace)."""

    def __init__(self, log: Path, prefix: list[str] = ()):
        self.port = _free_port()
        self.address = f"127.0.0.1:{self.port}"
        self.temp = tempfile.mkdtemp(prefix="rt", dir="/tmp")  # unix socket paths must stay short
        self.proc = subprocess.Popen([*prefix, RAY, "start", "--head", "--block", "--port", str(self.port),
                                      "--num-cpus", "2", "--temp-dir", self.temp, "--include-dashboard=false",
                                      "--disable-usage-stats"], stdout=log.open("w"), stderr=subprocess.STDOUT,
                                     start_new_session=True)
        deadline = time.monotonic() + 120
        while True:
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=1).close()
                break
            except OSError:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    self.stop()
                    raise RuntimeError(f"ray start failed: {log.read_text()[-2000:]}")
                time.sleep(0.5)

    def task_workers(self) -> list[int]:
        """Worker processes of this cluster running a task now."""
        pids = []
        for pid in _children(self.proc.pid):
            try:
                if Path(f"/proc/{pid}/cmdline").read_bytes().startswith(b"ray::_call"):
                    pids.append(pid)
            except OSError:
                pass
        return pids

    def stop(self) -> None:
        tree = [self.proc.pid, *_children(self.proc.pid)]
        for sig in (signal.SIGTERM, signal.SIGKILL):
            for pid in tree:
                try:
                    os.kill(pid, sig)
                except ProcessLookupError:
                    pass
            try:
                self.proc.wait(5)
                break
            except subprocess.TimeoutExpired:
                continue
        subprocess.run(["rm", "-rf", self.temp], check=False)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    c = Cluster(tmp_path_factory.mktemp("ray") / "head.log")
    yield c
    c.stop()


def _same_tree(a: Path, b: Path) -> None:
    files_a = sorted(p.relative_to(a) for p in a.rglob("*"))
    assert files_a == sorted(p.relative_to(b) for p in b.rglob("*"))
    different = [str(p) for p in files_a if (a / p).is_file() and not filecmp.cmp(a / p, b / p, shallow=False)]
    assert not different


def _kill_a_task_worker(cluster: Cluster, run: subprocess.Popen) -> int | None:
    """SIGKILL the first worker process of ``cluster`` seen running a task (1 s into it) while ``run`` lives;
    returns its pid, or None if none was seen within 120 s."""
    deadline = time.monotonic() + 120
    while run.poll() is None and time.monotonic() < deadline:
        workers = cluster.task_workers()
        if workers:
            time.sleep(1.0)  # inside the task by now
            try:
                os.kill(workers[0], signal.SIGKILL)
                return workers[0]
            except ProcessLookupError:
                continue
        time.sleep(0.2)
    return None


def test_local_path_does_not_import_ray():
    code = ("import sys, selfseg.generate.cli, selfseg.method.pseudolabels; from selfseg.executor import make_executor\n"
            "with make_executor('local', workers=1) as ex: assert ex.submit(abs, -2).result() == 2\n"
            "print('ray' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.stdout.strip() == "False", r.stderr


@pytest.mark.parametrize("extra, message", [
    (["--executor", "dask"], "--executor must be one of local, ray, got 'dask'"),
    (["--ray-address", "127.0.0.1:{port}"], "--ray-address needs --executor ray"),
    (["--executor", "ray", "--ray-address", "127.0.0.1:{port}"], "no Ray cluster reachable there"),
    (["--executor", "ray", "--ray-address", "nohost"], "must be 'auto' or HOST:PORT"),
])
def test_bad_executor_options_one_line(tmp_path, capsys, extra, message):
    port = _free_port()  # closed again: nothing listens there
    out = tmp_path / "out"
    t0 = time.monotonic()
    assert generate_scenes([*TINY, "--out", str(out), *(e.format(port=port) for e in extra)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert not out.exists() and time.monotonic() - t0 < 10


@pytest.mark.parametrize("extra", [["--ray-cpus-per-task", "3"], ["--ray-gpus-per-task", "1"]])
def test_task_larger_than_any_node_one_line(tmp_path, extra):
    """A task no node can hold (Ray would wait forever): rc 2, one line, nothing written (no GPU here)."""
    if extra[0] == "--ray-gpus-per-task" and Path("/dev/nvidia0").exists():
        pytest.skip("this machine has a GPU")
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "selfseg.generate.cli", *TINY, "--out", str(out), "--executor", "ray",
                        "--workers", "2", *extra], capture_output=True, text=True, timeout=300)
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("generate_scenes:")]
    assert r.returncode == 2 and len(lines) == 1 and "no node of the local Ray instance" in lines[0], r.stderr
    assert not out.exists()


def _scenes(rng: np.random.Generator) -> list[SceneGraph]:
    """Three scenes of two 4-node path components; features are noisy copies of shared patterns."""
    patterns = [rng.normal(size=(4, 8)) for _ in range(2)]
    scenes = []
    for s in range(3):
        feats = np.vstack([p + 0.05 * rng.normal(size=p.shape) for p in patterns])
        feats /= np.linalg.norm(feats, axis=1, keepdims=True)
        edges = np.array([[0, 1], [1, 2], [2, 3], [4, 5], [5, 6], [6, 7]])
        scenes.append(SceneGraph(f"s{s}", feats, edges, [np.arange(4), np.arange(4, 8)]))
    return scenes


def test_matching_and_registration_on_ray_equal_local():
    """match_all and the V4/pruning registrations give the same results on a private 2-CPU Ray instance."""
    scenes = _scenes(np.random.default_rng(0))
    serial = match_all(scenes, MatchConfig(workers=1), progress=False)
    rng = np.random.default_rng(1)
    clouds = [rng.uniform(-0.05, 0.05, size=(300, 3)) for _ in range(2)]
    pairs = [(c, c @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]) + 0.01) for c in clouds]
    cfg = PruneConfig()
    with make_executor("ray", workers=2) as ex:
        check_shared_folder(ex, tempfile.gettempdir())
        on_ray = match_all(scenes, MatchConfig(pairs_per_task=1), executor=ex, progress=False)
        regs = list(ex.map(register_clouds, [a for a, _ in pairs], [b for _, b in pairs], [cfg] * len(pairs)))
    assert len(serial) == 3 * 2 * 2 * 2
    assert sum(bool(m.result.node_map) for m in serial) >= 6  # the fixture has real matches to compare
    key = lambda m: (m.src_scene, m.src_comp, m.tgt_scene, m.tgt_comp, m.result.node_map, m.result.edge_map,  # noqa: E731
                     m.result.cost, m.result.status)
    assert [key(m) for m in on_ray] == [key(m) for m in serial]
    local = [register_clouds(a, b, cfg) for a, b in pairs]  # open3d's registration is not bit-reproducible
    for r, q in zip(regs, local):  # (even run twice in one process), so: equal to 1e-9
        assert r.keys() == q.keys() and np.allclose(r["T_tgt_src"], q["T_tgt_src"], rtol=0, atol=1e-9)
        assert r["fitness"] == pytest.approx(q["fitness"], abs=1e-9) and r["rmse"] == pytest.approx(q["rmse"], abs=1e-9)


@pytest.mark.slow
def test_generate_on_ray_identical_and_survives_a_killed_worker(cluster, tiny_dataset, tmp_path):
    """The tiny preset on a joined 2-CPU cluster, with one task's worker process killed mid-run: Ray re-runs
    the scene and the dataset is byte-identical to the local one (the pinned command's, as conftest makes it; no
    half-written scene left)."""
    out = tmp_path / "data"
    run = subprocess.Popen([sys.executable, "-m", "selfseg.generate.cli", *TINY, "--out", str(out), "--executor", "ray",
                            "--ray-address", cluster.address], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    killed = _kill_a_task_worker(cluster, run)
    stdout, stderr = run.communicate(timeout=900)  # a hang guard: 2 loaded cores need over 300 s
    assert killed is not None, "no task worker was seen running"
    assert run.returncode == 0, stderr
    assert "5 scenes generated" in stdout
    _same_tree(out, tiny_dataset)


@pytest.mark.slow
def test_the_pinned_command_pins_the_workers_of_a_cluster(cluster, tmp_path):
    """``generate_scenes`` pins itself (selfseg.generate.determinism); on a cluster started unpinned (as
    ``ray start`` is on any node) its workers start pinned too, so the scene is byte-identical to the local
    command's. Its control: unpinned workers (the in-process driver, below) give other bytes."""
    args = [*TINY, "--scenes", "1", "--frames", "6"]
    trees = {}
    for name, cmd, ray in (("local", [sys.executable, "-m", "selfseg.generate.cli"], []),
                           ("ray", [sys.executable, "-m", "selfseg.generate.cli"], ["--executor", "ray"]),
                           ("ray-unpinned", UNPINNED_COMMAND, ["--executor", "ray"])):
        extra = ["--ray-address", cluster.address] if ray else []
        r = subprocess.run([*cmd, *args, "--out", str(tmp_path / name), "--cache-dir", str(tmp_path / f"c-{name}"),
                            *ray, *extra], capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr
        trees[name] = tmp_path / name
    _same_tree(trees["local"], trees["ray"])
    flags = Path("/proc/cpuinfo").read_text().split() if Path("/proc/cpuinfo").exists() else []
    if "fma" in flags and "avx2" in flags:  # elsewhere libm has one variant (tests/test_cross_machine.py)
        with pytest.raises(AssertionError):
            _same_tree(trees["local"], trees["ray-unpinned"])


@pytest.mark.slow
def test_workers_that_start_otherwise_pinned_are_refused(tmp_path):
    """A cluster whose nodes start pinned, joined by an unpinned driver: the workers would compute other bytes,
    so the run stops with one line and rc 2."""
    env = ["env", *(f"{k}={v}" for k, v in pinned_vars(dict(os.environ)).items())]
    line = _refused_on_own_cluster(tmp_path, env, [*UNPINNED_COMMAND, *TINY, "--scenes", "1", "--frames", "2",
                                                   "--out", str(tmp_path / "d")])
    assert "started with its numerical libraries pinned, unlike this command" in line


def _refused_on_own_cluster(tmp_path: Path, prefix: list[str], cmd: list[str]) -> str:
    """Run generate_scenes ``cmd`` on a cluster started behind ``prefix``; it must stop with rc 2 and one
    ``generate_scenes:`` line, which is returned."""
    c = Cluster(tmp_path / "head.log", prefix)
    try:
        r = subprocess.run([*cmd, "--executor", "ray", "--ray-address", c.address], capture_output=True, text=True,
                           timeout=300)
    finally:
        c.stop()
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("generate_scenes:")]
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    return lines[0]


def test_probe_fails_when_workers_see_another_folder(tmp_path):
    """A cluster in its own mount namespace sees a tmpfs at the output folder, not this folder: rc 2, one line,
    nothing written here."""
    hidden = tmp_path / "shared"
    hidden.mkdir()
    prefix = ["unshare", "-m", "--propagation", "private", "sh", "-c", 'mount -t tmpfs none "$0" && exec "$@"',
              str(hidden)]
    if subprocess.run([*prefix, "true"], capture_output=True).returncode != 0:
        pytest.skip("no mount namespaces here (unshare -m needs CAP_SYS_ADMIN)")
    line = _refused_on_own_cluster(tmp_path, prefix, [sys.executable, "-m", "selfseg.generate.cli", *TINY, "--out",
                                                      str(hidden / "data")])
    assert f"{hidden}: a Ray worker on" in line and "shared by every node" in line
    assert list(hidden.iterdir()) == []


def test_shared_folder_probe_passes_and_cleans_up(tmp_path):
    with make_executor("local", workers=1) as ex:
        check_shared_folder(ex, tmp_path)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ExecutorError, match="workers must be at least 1"):
        make_executor("local", workers=0)


def _fold_records(out: Path) -> dict[str, dict]:
    """{file name: record less run-specific fields} of every fold result under ``out``."""
    drop = ("timings", "predictions_dir", "created_utc")
    return {p.name: {k: v for k, v in read_json(p).items() if k not in drop}
            for p in sorted((out / "scores").rglob("fold*.json"))}


@pytest.mark.parametrize("method, folds", [("depth-clustering", ["0", "1", "2"]), ("lccp-frame", ["0"])],
                         ids=["depth-clustering", "lccp-frame"])
def test_evaluate_folds_on_ray_equal_local(tiny_dataset, tmp_path, method, folds):
    """evaluate --executor ray: each fold is a Ray task (method sandbox, scoring, files) and gives the local
    run's records, frame scores and predictions: three folds at once (depth-clustering), and one fold of
    lccp-frame, whose compiled LCCP runs in the worker's sandbox (one fold of it is the suite's time budget)."""
    args = ["--method", method, "--data", str(tiny_dataset), "--quiet", "--folds", ",".join(folds)]
    assert evaluate([*args, "--out", str(tmp_path / "local")]) == 0
    assert evaluate([*args, "--out", str(tmp_path / "ray"), "--executor", "ray"]) == 0
    local, on_ray = _fold_records(tmp_path / "local"), _fold_records(tmp_path / "ray")
    assert sorted(local) == [f"fold{f}.json" for f in folds] and local == on_ray
    _same_tree(tmp_path / "local" / "predictions", tmp_path / "ray" / "predictions")
    frames = sorted(p.relative_to(tmp_path / "local") for p in (tmp_path / "local").rglob("*.frames.jsonl"))
    assert len(frames) == len(folds) and all(filecmp.cmp(tmp_path / "local" / f, tmp_path / "ray" / f, shallow=False)
                                    for f in frames)


@pytest.mark.parametrize("section, message", [
    ("{kind: dask}", "executor: kind must be one of local, ray, got 'dask'"),
    ("{kind: ray, workers: 2}", "unknown config key 'executor.workers'"),
    ("{kind: ray, ray_cpus_per_task: 4096}", "no node of the local Ray instance"),
])
def test_executor_section_of_the_yaml_config(tiny_dataset, tmp_path, capsys, section, message):
    """The YAML config's ``executor:`` section is read (a task no node holds proves Ray was asked) and checked:
    one line naming the problem, rc 2, nothing written; it is not part of the method's config."""
    cfg = tmp_path / "run.yaml"
    cfg.write_text(f"executor: {section}\n")
    out = tmp_path / "out"
    assert evaluate(["--method", "depth-clustering", "--data", str(tiny_dataset), "--config", str(cfg),
                     "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert not out.exists()


@pytest.mark.slow
def test_evaluate3d_on_a_cluster_survives_a_killed_worker(cluster, tiny_dataset, tmp_path):
    """evaluate3d's per-video stages as tasks on a joined 2-CPU cluster, one task's worker killed mid-stage:
    Ray re-runs it and Table II equals the local run's. On two of tiny's videos (a dataset is the videos its
    folder holds), one task per CPU, which is all the kill needs."""
    data = tmp_path / "two-videos"
    shutil.copytree(tiny_dataset, data, ignore=lambda d, names: names if Path(d).name == "videos" else [])
    for vid in sorted(p.name for p in (tiny_dataset / "videos").iterdir())[:2]:
        shutil.copytree(tiny_dataset / "videos" / vid, data / "videos" / vid)
    cmd = [sys.executable, "-c", "import sys; from selfseg.eval.cli import evaluate3d_main; sys.exit(evaluate3d_main())",
           "--data", str(data), "--rows", "lccp+symseg", "--quiet"]
    local = subprocess.run([*cmd, "--out", str(tmp_path / "local")], capture_output=True, text=True, timeout=900)
    assert local.returncode == 0, local.stderr
    run = subprocess.Popen([*cmd, "--out", str(tmp_path / "ray"), "--executor", "ray", "--ray-address",
                            cluster.address], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    killed = _kill_a_task_worker(cluster, run)
    stdout, stderr = run.communicate(timeout=900)
    assert killed is not None, "no task worker was seen running"
    assert run.returncode == 0, stderr
    (a,), (b,) = (list(_fold_records(tmp_path / d).values()) for d in ("local", "ray"))
    assert a["name"] == b["name"] == "lccp+symseg" and a["config_hash"] == b["config_hash"]
    assert b["metrics"] == a["metrics"] and b["per_video"] == a["per_video"]
