"""Cheating methods, one per known way around the ground-truth wall (the ten numbered routes and more), each a
module of its own written into a temporary folder and run through the real ``evaluate`` CLI, as a method
author would run it (``--method cheats.route:Route``).

Each cheat knows where the dataset and ``--out`` are (hard-coded) and looks for the ground truth of every
test frame it segments; it segments with it if found, else with the foreground as one segment, which is
what ``one-segment`` does. A cheat is blocked when it finds nothing (in its sandbox the files are not there)
and scores exactly ``one-segment``'s IoU, or when the run exits non-zero; no result file changes after the
run. Where a route still works without the sandbox (a plain process, ``--trust-method`` where no sandbox can
start), a second test shows it scoring 1.0 there: the cheat is real, the sandbox is what stops it.
"""
from __future__ import annotations

import concurrent.futures
import json
import os
import socket
import subprocess
import sys
import textwrap
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from selfseg.dataset import MASK_INST, SCENE_CAMERA, Dataset
from selfseg.eval.aggregate import SegmentationEvaluator
from selfseg.eval.cli import main as evaluate
from selfseg.eval.folds import EvalOptions
from selfseg.eval.layout import WORK_DIR
from selfseg.eval.protocol import run_fold
from selfseg.eval.sandbox import BWRAP_ENV, sandbox_unavailable
from selfseg.fileio import read_json
from selfseg.method_api import Method

ARGS = ["--folds", "0", "--frame-stride", "2", "--quiet"]
FAST = EvalOptions(frame_stride=2, n_boot=100)
NO_BWRAP = "/nonexistent/bwrap"  # SELFSEG_BWRAP pointing here: no sandbox can start (the fallback)

# Every cheat module starts with this: where the data is, and a base class that records what it found.
PRELUDE = '''
import glob, json, os, subprocess, sys, time
from pathlib import Path

import cv2
import numpy as np

from selfseg.dataset import MASK_INST, read_inst
from selfseg.method_api import Method

REAL = {real!r}  # the dataset's folder
OUT = {out!r}  # evaluate's --out
EXTRA = {extra!r}  # what the test tells this route (a copy's folder, a port, ...)


def mask(video_id, frame_id):
    return os.path.join(REAL, MASK_INST.format(video_id=video_id, frame_id=frame_id))


class Cheat(Method):
    """``look`` returns the frame's ground truth (an array), True (ground truth reached but not used), or
    why it found none; every look is noted in the work folder's seen.jsonl."""

    name = "cheat"

    def fit(self, train_videos):
        self.prepare(train_videos)

    def prepare(self, train_videos):
        pass

    def look(self, video, frame_id):
        raise NotImplementedError

    def segment(self, video, frame_id, fg_mask):
        try:
            found = self.look(video, frame_id)
        except Exception as e:  # noqa: BLE001
            found = repr(e)
        gt = found if isinstance(found, np.ndarray) else None
        with open(Path(self.workdir) / "seen.jsonl", "a") as f:
            f.write(json.dumps({{"found": gt is not None or found is True,
                                 "detail": found if isinstance(found, str) else ""}}) + "\\n")
        return gt.astype(np.uint16) if gt is not None else fg_mask.astype(np.uint16)
'''


@dataclass
class Route:
    id: str
    body: str  # the module's code after PRELUDE; defines class Route(Cheat)
    real_without_sandbox: bool = True  # the route reaches ground truth in a plain process


ROUTES = [
    # 1: the class declares needs_ground_truth: it is not the class's to say (the registry's; user: a flag)
    Route("1-class-says-needs-ground-truth", '''
        class Route(Cheat):
            name = "cheat-class-gt"
            needs_ground_truth = True

            def look(self, video, frame_id):
                if hasattr(video, "inst"):
                    return video.inst(frame_id)
                p = Path(video.root) / MASK_INST.format(video_id=video.video_id, frame_id=frame_id)
                return read_inst(p) if p.is_file() else f"{type(video).__name__}, no {p}"
    ''', real_without_sandbox=False),
    # 2: switch the in-process check off, then read the mask where it is
    Route("2-clear-guard-state", '''
        class Route(Cheat):
            name = "cheat-guard-state"

            def look(self, video, frame_id):
                import selfseg.guard as guard
                guard._guard_roots = []
                return read_inst(mask(video.video_id, frame_id))
    '''),
    # 3: libc's __open_2 through ctypes (no audit event at all)
    Route("3-ctypes-open", '''
        class Route(Cheat):
            name = "cheat-ctypes"

            def look(self, video, frame_id):
                import ctypes
                libc = ctypes.CDLL(None, use_errno=True)
                fd = getattr(libc, "__open_2")(os.fsencode(mask(video.video_id, frame_id)), os.O_RDONLY)
                if fd < 0:
                    return f"__open_2: {os.strerror(ctypes.get_errno())}"
                data = os.read(fd, 1 << 22)
                os.close(fd)
                return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    '''),
    # 4: another program reads it (subprocess starts it through subprocess._fork_exec)
    Route("4-program-reads-it", '''
        class Route(Cheat):
            name = "cheat-program"

            def look(self, video, frame_id):
                done = subprocess.run(["cat", mask(video.video_id, frame_id)], capture_output=True)
                if done.returncode:
                    return done.stderr.decode()
                return cv2.imdecode(np.frombuffer(done.stdout, np.uint8), cv2.IMREAD_UNCHANGED)
    '''),
    # 5: the evaluator's memory through /proc (it holds the test frames' ground truth while the method runs)
    Route("5-evaluator-memory", '''
        class Route(Cheat):
            name = "cheat-proc-mem"

            def look(self, video, frame_id):
                seen = []
                for pid in filter(str.isdigit, os.listdir("/proc")):
                    try:
                        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\\0", b" ").decode(errors="replace")
                    except OSError:
                        continue
                    seen.append(cmd[:60])
                    evaluator = "pytest" in cmd or "selfseg.eval.cli" in cmd or "bin/evaluate" in cmd
                    if evaluator and os.path.basename(cmd.split()[0]) != "bwrap":  # read its memory
                        for line in Path(f"/proc/{pid}/maps").read_text().splitlines():
                            lo, hi = (int(x, 16) for x in line.split()[0].split("-"))
                            if line.split()[1].startswith("rw"):
                                with open(f"/proc/{pid}/mem", "rb") as mem:
                                    mem.seek(lo)
                                    return len(mem.read(min(hi - lo, 4096))) > 0
                return f"processes seen: {seen}"
    '''),
    # 6: patch the evaluator's scorer while the module is imported (it would score ground truth against itself)
    Route("6-patch-scorer-at-import", '''
        from selfseg.eval import aggregate

        _score = aggregate.SegmentationEvaluator.process
        aggregate.SegmentationEvaluator.process = lambda self, v, f, pred, gt: _score(self, v, f, gt, gt)


        class Route(Cheat):
            name = "cheat-patch-scorer"

            def look(self, video, frame_id):
                return "scores itself"
    ''', real_without_sandbox=False),
    # 7: copy the videos somewhere while the module is imported, read the copy later
    Route("7-copy-at-import", '''
        import shutil

        try:
            shutil.copytree(os.path.join(REAL, "videos"), EXTRA)
        except Exception as e:  # noqa: BLE001
            COPY_ERROR = repr(e)


        class Route(Cheat):
            name = "cheat-copy-at-import"

            def look(self, video, frame_id):
                p = Path(EXTRA) / video.video_id / "mask_inst" / f"{frame_id:06d}.png"
                return read_inst(p) if p.is_file() else f"no copy ({COPY_ERROR})"
    ''', real_without_sandbox=False),
    # 8: a second copy of the dataset on disk, found by its dataset_info.json (and where it was told it is)
    Route("8-second-copy", '''
        class Route(Cheat):
            name = "cheat-second-copy"

            def prepare(self, train_videos):
                self.copies, deadline = [EXTRA], time.monotonic() + 3
                for top, dirs, files in os.walk("/"):
                    dirs[:] = [d for d in dirs if os.path.join(top, d) not in ("/proc", "/sys", "/dev", "/usr")
                               and d not in ("site-packages", ".git", ".venv")]
                    if "dataset_info.json" in files:  # a dataset: note it, and list none of its folders
                        self.copies.append(top)
                        dirs[:] = []
                    if time.monotonic() > deadline:
                        break

            def look(self, video, frame_id):
                for root in self.copies:
                    p = Path(root) / MASK_INST.format(video_id=video.video_id, frame_id=frame_id)
                    if p.is_file():
                        return read_inst(p)
                return f"datasets seen: {self.copies}"
    '''),
    # 9: the predictions an earlier oracle run left in --out
    Route("9-oracle-predictions", '''
        class Route(Cheat):
            name = "cheat-oracle-predictions"

            def look(self, video, frame_id):
                for p in glob.glob(f"{OUT}/predictions/oracle/*/{video.video_id}/{frame_id:06d}.png"):
                    return read_inst(p)
                return "no oracle predictions"
    '''),
    # also: catch the in-process check's refusal, erase its record, switch it off and read again
    Route("caught-refusal-erased", '''
        class Route(Cheat):
            name = "cheat-erase-record"

            def look(self, video, frame_id):
                import selfseg.guard as guard
                try:
                    return read_inst(mask(video.video_id, frame_id))
                except guard.GroundTruthAccessError:
                    guard.ground_truth_attempts.clear()
                    guard._guard_roots = []
                    return read_inst(mask(video.video_id, frame_id))
    '''),
    # also: OpenCV's FileStorage reads the JSON ground truth (out of the in-process check's sight)
    Route("cv2-filestorage", '''
        class Route(Cheat):
            name = "cheat-filestorage"

            def look(self, video, frame_id):
                fs = cv2.FileStorage(os.path.join(REAL, "videos", video.video_id, "scene_gt.json"),
                                     cv2.FILE_STORAGE_READ)
                return (fs.isOpened() and fs.getNode(str(frame_id)).isSeq()) or "FileStorage opened nothing"
    '''),
    # also: ask a server for it (a running Ray cluster, a helper on localhost); EXTRA is its port
    Route("network", '''
        import socket


        class Route(Cheat):
            name = "cheat-network"

            def look(self, video, frame_id):
                with socket.create_connection(("127.0.0.1", EXTRA), timeout=5) as s:
                    s.sendall(f"{video.video_id} {frame_id}\\n".encode())
                    data = b"".join(iter(lambda: s.recv(1 << 16), b""))
                return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    '''),
]


@pytest.fixture(scope="module")
def honest_iou(analytic_dataset, tmp_path_factory) -> float:
    """IoU of the honest fallback every cheat uses (the foreground as one segment) on the cheats' frames."""
    out = tmp_path_factory.mktemp("honest")
    assert evaluate(["--method", "one-segment", "--data", str(analytic_dataset), "--out", str(out), *ARGS]) == 0
    return read_json(out / "scores/analytic/one-segment/fold0.json")["metrics"]["IoU"]


def _serve_masks(dataset: Path) -> int:
    """A localhost server (daemon thread) answering "<video> <frame>" with that frame's mask PNG; its port."""
    server = socket.create_server(("127.0.0.1", 0))

    def serve():
        while True:
            conn, _ = server.accept()
            with conn:
                video, frame = conn.makefile().readline().split()
                conn.sendall((dataset / MASK_INST.format(video_id=video, frame_id=int(frame))).read_bytes())

    threading.Thread(target=serve, daemon=True).start()
    return server.getsockname()[1]


def _extra(route: Route, dataset: Path, tmp_path: Path):
    import shutil

    if route.id == "8-second-copy":
        shutil.copytree(dataset, tmp_path / "copy-of-the-data")
        return str(tmp_path / "copy-of-the-data")
    if route.id == "network":
        return _serve_masks(dataset)
    return str(tmp_path / "stash")


def run_cheat(body: str, dataset: Path, tmp_path: Path, monkeypatch, capsys, *argv, extra=None):
    """Write ``cheats/route.py`` (PRELUDE + body) and run ``evaluate --method cheats.route:Route`` in this
    process; returns (exit code, stderr, the fold-0 record or None, the cheat's seen.jsonl lines)."""
    out = tmp_path / "out"
    package = tmp_path / "userpath" / "cheats"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "route.py").write_text(PRELUDE.format(real=str(dataset), out=str(out), extra=extra)
                                      + textwrap.dedent(body))
    monkeypatch.syspath_prepend(str(tmp_path / "userpath"))
    capsys.readouterr()
    code = evaluate(["--method", "cheats.route:Route", "--data", str(dataset), "--out", str(out), *ARGS, *argv])
    err = capsys.readouterr().err
    assert "cheats" not in sys.modules  # the method's code never ran in the evaluator
    records = [p for p in (out / "scores").glob("*/*/fold0.json") if p.parent.name != "oracle"]
    seen = [json.loads(x) for p in (out / "work").glob("*/*/fold0/seen.jsonl") for x in p.read_text().splitlines()]
    return code, err, read_json(records[0]) if records else None, seen


def test_the_sandbox_starts_here():
    """The suite runs where user namespaces work (make test installs bubblewrap); the fallback is tested
    separately with SELFSEG_BWRAP pointing at a binary that does not exist."""
    assert sandbox_unavailable() is None


@pytest.mark.slow
@pytest.mark.parametrize("route", ROUTES, ids=lambda r: r.id)
def test_route_is_blocked(route, analytic_dataset, tmp_path, monkeypatch, capsys, honest_iou):
    if route.id == "9-oracle-predictions":
        assert evaluate(["--method", "oracle", "--data", str(analytic_dataset), "--out", str(tmp_path / "out"),
                         *ARGS]) == 0
    code, err, rec, seen = run_cheat(route.body, analytic_dataset, tmp_path, monkeypatch, capsys,
                                     extra=_extra(route, analytic_dataset, tmp_path))
    assert code == 0, err
    assert seen and not any(s["found"] for s in seen), seen
    assert rec["isolation"] == "sandbox" and rec["ground_truth"] == "none"
    assert rec["metrics"]["IoU"] == honest_iou and rec["ground_truth_attempts"] == []
    if route.id == "6-patch-scorer-at-import":
        assert SegmentationEvaluator.process.__module__ == "selfseg.eval.aggregate"  # the evaluator's own
    if route.id == "7-copy-at-import":
        assert not (tmp_path / "stash").exists()


@pytest.mark.slow
@pytest.mark.parametrize("route", [r for r in ROUTES if r.real_without_sandbox], ids=lambda r: r.id)
def test_route_is_real_without_the_sandbox(route, analytic_dataset, tmp_path, monkeypatch, capsys):
    """The same module in a plain process (no sandbox can start; --trust-method) reaches ground truth."""
    monkeypatch.setenv(BWRAP_ENV, NO_BWRAP)
    if route.id == "9-oracle-predictions":
        assert evaluate(["--method", "oracle", "--data", str(analytic_dataset), "--out", str(tmp_path / "out"),
                         *ARGS]) == 0
    code, err, rec, seen = run_cheat(route.body, analytic_dataset, tmp_path, monkeypatch, capsys, "--trust-method",
                                     extra=_extra(route, analytic_dataset, tmp_path))
    assert code == 0, err
    assert seen and all(s["found"] for s in seen), seen
    assert rec["isolation"] == "unsandboxed"
    if route.id not in ("5-evaluator-memory", "cv2-filestorage"):  # those reach it without using it
        assert rec["metrics"]["IoU"] == 1.0


# 10: a double-forked grandchild outlives the method's process and rewrites the fold's result after scoring
OUTLIVE = '''
    class Route(Cheat):
        name = "cheat-outlive"

        def prepare(self, train_videos):
            if os.fork() == 0:
                os.setsid()
                if os.fork() == 0:  # beats every 50 ms for 30 s; rewrites the result as soon as it is there
                    for _ in range(600):
                        with open(Path(self.workdir) / "heartbeat", "a") as f:
                            f.write(".")
                        for p in glob.glob(f"{OUT}/scores/*/cheat-outlive/fold0.json"):
                            rec = json.loads(Path(p).read_text())
                            rec["metrics"]["IoU"] = 1.0
                            Path(p).write_text(json.dumps(rec))
                            os._exit(0)
                        time.sleep(0.05)
                os._exit(0)
            os.wait()

        def look(self, video, frame_id):
            return "honest; my grandchild does the rest"
'''


def _heartbeats(out: Path) -> int:
    return sum(p.stat().st_size for p in (out / "work").rglob("heartbeat"))


@pytest.mark.slow
def test_grandchild_cannot_outlive_the_sandbox(analytic_dataset, tmp_path, monkeypatch, capsys, honest_iou):
    code, err, rec, _ = run_cheat(OUTLIVE, analytic_dataset, tmp_path, monkeypatch, capsys)
    assert code == 0, err
    fold0 = next((tmp_path / "out/scores").glob("*/cheat-outlive/fold0.json"))
    before, beats = fold0.read_bytes(), _heartbeats(tmp_path / "out")
    time.sleep(1.5)  # a survivor beats every 50 ms
    assert beats > 0 and _heartbeats(tmp_path / "out") == beats  # it ran, and died with the sandbox
    assert fold0.read_bytes() == before and rec["metrics"]["IoU"] == honest_iou
    capsys.readouterr()
    assert evaluate(["--method", "cheats.route:Route", "--data", str(analytic_dataset), "--out",
                     str(tmp_path / "out"), "--folds", "0", "--frame-stride", "2"]) == 0
    assert "reusing" in capsys.readouterr().err and fold0.read_bytes() == before


@pytest.mark.slow
def test_grandchild_outlives_a_plain_process(analytic_dataset, tmp_path, monkeypatch, capsys):
    """Without the sandbox the same grandchild survives and rewrites the scored result: what --trust-method
    gives up."""
    monkeypatch.setenv(BWRAP_ENV, NO_BWRAP)
    code, err, _, _ = run_cheat(OUTLIVE, analytic_dataset, tmp_path, monkeypatch, capsys, "--trust-method")
    assert code == 0, err
    fold0 = next((tmp_path / "out/scores").glob("*/cheat-outlive/fold0.json"))
    deadline = time.monotonic() + 30
    while read_json(fold0)["metrics"]["IoU"] < 1.0 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert read_json(fold0)["metrics"]["IoU"] == 1.0


# also: the method's process writes its prediction as a link to a ground-truth file the evaluator can see
LINKED_PREDICTION = '''
    import selfseg.eval.protocol as protocol


    def _link(path, inst):
        import selfseg.guard
        selfseg.guard._guard_roots = []  # the in-process check would refuse the link
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        os.symlink(mask(path.parent.name, int(path.stem)), path)


    protocol.write_inst = _link  # in the method's own process: how its predictions get written


    class Route(Cheat):
        name = "cheat-linked-prediction"

        def look(self, video, frame_id):
            return "my predictions will point at the masks"
'''


@pytest.mark.slow
@pytest.mark.parametrize("sandboxed", [True, False], ids=["sandbox", "plain-process"])
def test_prediction_links_are_refused(analytic_dataset, tmp_path, monkeypatch, capsys, sandboxed):
    if not sandboxed:
        monkeypatch.setenv(BWRAP_ENV, NO_BWRAP)
    code, err, rec, _ = run_cheat(LINKED_PREDICTION, analytic_dataset, tmp_path, monkeypatch, capsys,
                                  *([] if sandboxed else ["--trust-method"]))
    assert code == 2 and "is not a plain file" in err and rec is None, err
    assert len(err.strip().splitlines()) == 1 + (not sandboxed)  # the plain process's note, then the error
    assert not list((tmp_path / "out/predictions").rglob("*.png"))


@pytest.mark.slow
def test_what_a_method_sees(analytic_dataset, tmp_path, monkeypatch, capsys):
    """Inside: its inputs (the unlabeled view), its own folders and the system; not the dataset, --out's other
    folders, $HOME, other processes or the network; its inputs and the environment are read-only."""
    body = '''
        class Route(Cheat):
            name = "cheat-inventory"

            def prepare(self, train_videos):
                view = Path(train_videos[0].root)
                video = view / "videos" / train_videos[0].video_id

                def writable(p):
                    try:
                        Path(p, ".probe").write_text("x")
                        return True
                    except OSError:
                        return False

                def connects():
                    import socket
                    try:
                        socket.create_connection(("1.1.1.1", 53), timeout=2).close()
                        return True
                    except OSError:
                        return False
                inventory = {
                    "dataset": os.path.exists(REAL), "out_scores": os.path.exists(os.path.join(OUT, "scores")),
                    "home": os.path.exists(EXTRA), "HOME": os.environ["HOME"],
                    "home_files": os.listdir(os.environ["HOME"]), "view_videos": sorted(os.listdir(view / "videos")),
                    "view_entries": sorted(os.listdir(video)),
                    "processes": len([p for p in os.listdir("/proc") if p.isdigit()]),
                    "view_writable": writable(video), "venv_writable": writable(sys.prefix),
                    "workdir_writable": writable(self.workdir), "run_folder_writable": writable(Path(self.workdir).parent),
                    "stage_root": None if self.stage_root is None else str(self.stage_root), "network": connects(),
                    "program": subprocess.run(["sh", "-c", "echo started"], capture_output=True, text=True).stdout,
                }
                (Path(self.workdir) / "inventory.json").write_text(json.dumps(inventory))

            def look(self, video, frame_id):
                return None
    '''
    (tmp_path / "home").mkdir()
    (tmp_path / "home/secret.txt").write_text("the evaluator's own files")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    code, err, rec, _ = run_cheat(body, analytic_dataset, tmp_path, monkeypatch, capsys,
                                  extra=str(tmp_path / "home/secret.txt"))
    assert code == 0, err
    seen = read_json(next((tmp_path / "out/work").rglob("inventory.json")))
    assert seen["dataset"] is False and seen["out_scores"] is False and seen["home"] is False
    assert seen["HOME"] != str(tmp_path / "home") and seen["home_files"] == []
    assert seen["view_videos"] == Dataset(analytic_dataset).video_ids
    assert seen["view_entries"] == ["depth", "rgb", "scene_camera.json"]  # no labels
    assert seen["processes"] <= 3  # bwrap's init, the method's process, sh
    assert not seen["view_writable"] and not seen["venv_writable"] and not seen["network"]
    assert seen["workdir_writable"] and seen["run_folder_writable"]
    work = tmp_path / "out" / WORK_DIR.format(name="cheat-inventory", dataset="analytic", fold=0)
    assert (work.parent / ".probe").is_file()  # no labels: its folds share the run's folder
    assert seen["stage_root"] is None and seen["program"] == "started\n"  # a user's method: no shared stages


@pytest.mark.slow
def test_training_labels_only_with_the_flag(analytic_dataset, tmp_path, monkeypatch, capsys, honest_iou):
    """--method-needs-ground-truth: the training videos' labels, never the test videos'; recorded, named
    <name>@train-labels, marked in the leaderboard; the fold's own work folder only."""
    body = ROUTES[0].body + '''
        class Labeled(Route):
            name = "cheat-flagged"

            def prepare(self, train_videos):
                labels = {v.video_id: int(v.inst(v.frame_ids[0]).max()) for v in train_videos}
                (Path(self.workdir).parent / "left-for-other-folds").write_text(json.dumps(labels))
                (Path(self.workdir) / "train.json").write_text(json.dumps({"labels": labels}))
    '''
    code, err, _, seen = run_cheat(body, analytic_dataset, tmp_path, monkeypatch, capsys)
    assert code == 0 and not any(s["found"] for s in seen)  # without the flag: as route 1
    out = tmp_path / "out"
    capsys.readouterr()
    argv = ["--method", "cheats.route:Labeled", "--data", str(analytic_dataset), "--out", str(out), *ARGS]
    assert evaluate(argv + ["--method-needs-ground-truth"]) == 0, capsys.readouterr().err
    rec = read_json(out / "scores/analytic/cheat-flagged@train-labels/fold0.json")
    assert rec["options"]["method_needs_ground_truth"] and rec["ground_truth"] == "train"
    assert rec["metrics"]["IoU"] == honest_iou  # the test videos' labels were not there
    work = out / WORK_DIR.format(name="cheat-flagged@train-labels", dataset="analytic", fold=0)
    train = read_json(work / "train.json")
    assert sorted(train["labels"]) == rec["train_videos"] and all(n > 0 for n in train["labels"].values())
    assert not (work.parent / "left-for-other-folds").exists()  # given labels: only its fold's folder is kept
    seen = [json.loads(x) for x in (work / "seen.jsonl").read_text().splitlines()]
    assert seen and not any(s["found"] for s in seen)

    from selfseg.eval.leaderboard import main as build

    assert build(["--results", str(out), "--out", str(tmp_path / "boards")]) == 0
    board = (tmp_path / "boards/analytic.md").read_text()
    assert "cheat-flagged@train-labels** *(given training labels)*" in board
    assert evaluate(["--method", "oracle", "--method-needs-ground-truth", "--data", str(analytic_dataset),
                     "--out", str(out), *ARGS]) == 2


def test_registry_decides_which_labels_a_method_gets():
    """needs_ground_truth is the registry entry's: every class that claims it is registered with labels, and
    the other way round (evaluate reads the registry, never the class)."""
    from selfseg.registry import GROUND_TRUTH, get_method_class, method_names

    assert {n for n in method_names() if get_method_class(n).needs_ground_truth} == set(GROUND_TRUTH)
    assert GROUND_TRUTH == {"supervised": "train", "ours-gt-merging": "train", "oracle": "all"}


@pytest.mark.slow
def test_without_a_sandbox_user_methods_need_trust(analytic_dataset, tmp_path, monkeypatch, capsys):
    """No sandbox can start (SELFSEG_BWRAP names no binary): a user's method is refused in one line, exit 2,
    unless --trust-method; a built-in one runs in a plain process with the in-process check; both marked."""
    monkeypatch.setenv(BWRAP_ENV, NO_BWRAP)
    body = 'class Route(Cheat):\n    name = "honest"\n\n    def look(self, video, frame_id):\n        return None\n'
    code, err, rec, _ = run_cheat(body, analytic_dataset, tmp_path, monkeypatch, capsys)
    assert code == 2 and rec is None and len(err.strip().splitlines()) == 1
    assert "no sandbox can be started here" in err and NO_BWRAP in err and "--trust-method" in err
    out = tmp_path / "out"
    assert evaluate(["--method", "cheats.route:Route", "--trust-method", "--data", str(analytic_dataset),
                     "--out", str(out), *ARGS]) == 0
    assert evaluate(["--method", "one-segment", "--data", str(analytic_dataset), "--out", str(out), *ARGS]) == 0
    err = capsys.readouterr().err
    assert err.count("runs unsandboxed") == 2 and len(err.strip().splitlines()) == 2
    for name in ("honest", "one-segment"):
        assert read_json(out / f"scores/analytic/{name}/fold0.json")["isolation"] == "unsandboxed"

    from selfseg.eval.leaderboard import main as build

    assert build(["--results", str(out), "--out", str(tmp_path / "boards")]) == 0
    assert "**honest** *(unsandboxed)*" in (tmp_path / "boards/analytic.md").read_text()


class CheatOpen(Method):
    """Opens a training video's mask by the path of the folder it was given (an honest mistake)."""

    name = "cheat-open"

    def fit(self, train_videos):
        v = train_videos[0]
        open(Path(v.root) / MASK_INST.format(video_id=v.video_id, frame_id=0), "rb").read()


@pytest.mark.parametrize("sandboxed", [True, False], ids=["sandbox", "plain-process"])
def test_second_line_names_the_attempt(analytic_dataset, tmp_path, monkeypatch, sandboxed):
    """The in-process check, sandboxed or not: an attempt is refused, the fold is rejected with a record."""
    from selfseg.guard import GroundTruthAccessError

    if not sandboxed:
        monkeypatch.setenv(BWRAP_ENV, NO_BWRAP)
    with pytest.raises(GroundTruthAccessError, match="mask_inst"):
        run_fold(CheatOpen, None, Dataset(analytic_dataset), 0, tmp_path, FAST, progress=False)
    rejected = read_json(next((tmp_path / "rejected").glob("*/*/fold0.json")))
    assert rejected["ground_truth_attempts"] and rejected["isolation"] == ("sandbox" if sandboxed else "unsandboxed")
    assert not (tmp_path / "scores").exists()


# ---- what a method may still do ------------------------------------------------------------------
class PosesPeek(Method):
    """Reads camera poses straight from the scene_camera.json it can see; writes what it found."""

    name = "poses-peek"

    def fit(self, train_videos):
        cams = read_json(Path(train_videos[0].root) / SCENE_CAMERA.format(video_id=train_videos[0].video_id))
        (self.workdir / "t.json").write_text(json.dumps([c["cam_t_w2c"] for c in cams.values()]))

    def segment(self, video, frame_id, fg_mask):
        return fg_mask.astype(np.uint16)


@pytest.mark.parametrize("poses_given", [False, True])
def test_poses_only_with_poses_given(analytic_dataset, tmp_path, poses_given):
    ds = Dataset(analytic_dataset)
    options = EvalOptions(frame_stride=2, n_boot=100, poses_given=poses_given)
    run_fold(PosesPeek, None, ds, 0, tmp_path, options, progress=False)
    t = np.array(json.loads((tmp_path / WORK_DIR.format(name="poses-peek", dataset=ds.name, fold=0) / "t.json").read_text()))
    assert (np.abs(t).max() > 0) == poses_given  # the real orbit is never at the origin


def _square(x):
    return x * x


class PoolUser(Method):
    """Process pools (forked and spawned workers, as ``ours`` matches scene pairs), programs and matplotlib
    (which runs fc-list on first use, with an empty HOME here): all allowed in the sandbox."""

    name = "pool-user"

    def fit(self, train_videos):
        import multiprocessing

        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        for ctx in ("fork", "spawn"):
            with concurrent.futures.ProcessPoolExecutor(2, mp_context=multiprocessing.get_context(ctx)) as pool:
                assert list(pool.map(_square, [1, 2, 3])) == [1, 4, 9]
        assert subprocess.run(["true"]).returncode == 0
        plt.figure().text(0.5, 0.5, "fonts")
        plt.savefig(self.workdir / "fonts.png")

    def segment(self, video, frame_id, fg_mask):
        return fg_mask.astype(np.uint16)


def test_pools_programs_and_matplotlib_work(analytic_dataset, tmp_path):
    rec = run_fold(PoolUser, None, Dataset(analytic_dataset), 0, tmp_path, FAST, progress=False)
    assert rec["metrics"]["n_frames"] > 0 and rec["ground_truth_attempts"] == [] and rec["isolation"] == "sandbox"
    assert (tmp_path / WORK_DIR.format(name="pool-user", dataset="analytic", fold=0) / "fonts.png").stat().st_size


class Burner(Method):
    """Burns about half a second of CPU in fit and writes how much it burned (s) to its work folder."""

    name = "burner"

    def fit(self, train_videos):
        start, x = time.process_time(), 0
        while time.process_time() - start < 0.5:
            x += 1
        (self.workdir / "cpu_s").write_text(str(time.process_time() - start))

    def segment(self, video, frame_id, fg_mask):
        return fg_mask.astype(np.uint16)


def test_a_sandboxed_methods_cpu_time_reaches_the_caller(analytic_dataset, tmp_path):
    """The CPU time spent inside the sandbox is counted in the caller's RUSAGE_CHILDREN, which is what the
    benchmark's steps record (lost when bwrap's own init reaps the method's process)."""
    import resource

    def cpu():
        u = resource.getrusage(resource.RUSAGE_CHILDREN)
        return u.ru_utime + u.ru_stime

    before = cpu()
    rec = run_fold(Burner, None, Dataset(analytic_dataset), 0, tmp_path, FAST, progress=False)
    assert rec["isolation"] == "sandbox"
    burned = float((tmp_path / WORK_DIR.format(name="burner", dataset="analytic", fold=0) / "cpu_s").read_text())
    assert burned >= 0.5 and cpu() - before >= burned


PRIORITY = '''
from pathlib import Path

from selfseg.method_api import Method


class Priority(Method):
    """Writes the scheduling autogroup its process runs in to its work folder."""

    name = "priority"

    def fit(self, train_videos):
        (self.workdir / "autogroup").write_text(Path("/proc/self/autogroup").read_text())

    def segment(self, video, frame_id, fg_mask):
        return fg_mask.astype(np.uint16)
'''


@pytest.mark.skipif(not Path("/proc/self/autogroup").exists(), reason="the kernel has no scheduling autogroups")
@pytest.mark.parametrize("sandboxed", [True, False], ids=["sandbox", "plain-process"])
def test_a_niced_evaluation_keeps_its_method_niced(analytic_dataset, tmp_path, sandboxed):
    """`evaluate` run from a session whose autogroup has nice 7: the method's process, in a session of its own
    (a new autogroup, which the kernel starts at nice 0), runs at nice 7 too."""
    (tmp_path / "prio.py").write_text("import numpy as np\n" + PRIORITY)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    if not sandboxed:
        env[BWRAP_ENV] = NO_BWRAP
    cmd = [sys.executable, "-c", "import sys; from selfseg.eval.cli import main; sys.exit(main())",
           "--method", "prio:Priority", "--data", str(analytic_dataset), "--out", str(tmp_path / "out"), *ARGS,
           *([] if sandboxed else ["--trust-method"])]
    # the shell sets its new session's autogroup, then becomes the evaluator
    subprocess.run(["sh", "-c", 'echo 7 > /proc/self/autogroup && exec "$@"', "sh", *cmd], env=env, check=True,
                   start_new_session=True)
    group = (tmp_path / "out" / WORK_DIR.format(name="priority", dataset="analytic", fold=0) / "autogroup").read_text()
    assert group.split()[-2:] == ["nice", "7"], group
    # not this test's group (which reads empty where the test runs in the default autogroup: a session never
    # started with setsid, as under CI's runner)
    assert group.split()[0] not in Path("/proc/self/autogroup").read_text().split()[:1]
    rec = read_json(tmp_path / "out/scores/analytic/priority/fold0.json")
    assert rec["isolation"] == ("sandbox" if sandboxed else "unsandboxed")
