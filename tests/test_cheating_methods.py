"""Cheating methods, one per known way around the ground-truth wall: each is blocked or detected.

Methods run in their own process and see only an unlabeled copy of the dataset
(:func:`selfseg.eval.protocol.unlabeled_view`), so a cheat needs the real path from elsewhere: here
the environment variable ``CHEAT_ROOT`` (inherited by the method's process) plays the part of a
guessed or hard-coded path. A detected attempt, even one the method catches, stops the fold: no score
is written and ``rejected/.../fold0.json`` lists ``ground_truth_attempts``.
"""
from __future__ import annotations

import concurrent.futures
import ctypes
import inspect
import json
import multiprocessing
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from cv2 import imread  # bound before the method runs: the guard must still see it

from selfseg.dataset import MASK_INST, SCENE_CAMERA, SCENE_GT, Dataset, GroundTruthAccessError, read_inst
from selfseg.eval.protocol import WORK_DIR, EvalOptions, run_fold
from selfseg.fileio import read_json
from selfseg.method_api import Method

FAST = EvalOptions(frame_stride=2, n_boot=100)
VIDEO = "000000"


def _mask(frame: int = 0) -> str:
    """A ground-truth file of the real dataset, reached through the 'guessed' path."""
    return os.path.join(os.environ["CHEAT_ROOT"], MASK_INST.format(video_id=VIDEO, frame_id=frame))


class Cheat(Method):
    """Segments with the foreground as one segment; subclasses try to read ground truth in ``fit``."""

    def fit(self, train_videos):
        self.cheat()

    def cheat(self):
        raise NotImplementedError

    def segment(self, video, frame_id, fg_mask):
        return fg_mask.astype(np.uint16)


class ThreadCheat(Cheat):
    name = "cheat-thread"

    def cheat(self):
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            pool.submit(read_inst, _mask()).result()


class CatchCheat(Cheat):
    """Catches the refusal and carries on: still detected."""

    name = "cheat-catch"

    def cheat(self):
        try:
            read_inst(_mask())
        except GroundTruthAccessError:
            pass


class ImportTimeCheat(Cheat):
    name = "cheat-import"
    if os.environ.get("CHEAT_AT_IMPORT"):  # runs when the method's module is imported
        try:
            open(os.path.join(os.environ["CHEAT_ROOT"], SCENE_GT.format(video_id=VIDEO))).read()
        except GroundTruthAccessError:
            pass

    def cheat(self):
        pass


class InitCheat(Cheat):
    name = "cheat-init"

    def __init__(self, config=None, workdir=None):
        super().__init__(config, workdir)
        try:
            self.copied = read_inst(_mask())
        except GroundTruthAccessError:
            self.copied = None

    def cheat(self):
        pass


class EarlyImreadCheat(Cheat):
    name = "cheat-imread"

    def cheat(self):
        imread(_mask(), -1)


class VideoCaptureCheat(Cheat):
    name = "cheat-capture"

    def cheat(self):
        import cv2

        cv2.VideoCapture(_mask().replace("000000.png", "%06d.png")).read()


class EmptyCaptureCheat(Cheat):
    name = "cheat-capture-open"

    def cheat(self):
        import cv2

        cv2.VideoCapture().open(_mask().replace("000000.png", "%06d.png"))


class Open3dCheat(Cheat):
    name = "cheat-open3d"

    def cheat(self):
        import open3d as o3d

        o3d.io.read_image(_mask())


class ProcRootCheat(Cheat):
    name = "cheat-proc-root"

    def cheat(self):
        open("/proc/self/root" + os.path.abspath(_mask()), "rb").read()


class DirFdCheat(Cheat):
    name = "cheat-dir-fd"

    def cheat(self):
        fd = os.open(os.path.join(os.environ["CHEAT_ROOT"], "videos", VIDEO), os.O_RDONLY)
        os.close(os.open(os.path.join("mask_inst", "000000.png"), os.O_RDONLY, dir_fd=fd))


class SubprocessCheat(Cheat):
    name = "cheat-subprocess"

    def cheat(self):
        subprocess.run(["cat", _mask()], capture_output=True)


def _read_in_child(path, queue):
    queue.put(read_inst(path))


class SpawnCheat(Cheat):
    name = "cheat-spawn"

    def cheat(self):
        ctx = multiprocessing.get_context("spawn")
        queue = ctx.Queue()
        ctx.Process(target=_read_in_child, args=(_mask(), queue)).start()


class CtypesCheat(Cheat):
    name = "cheat-ctypes"

    def cheat(self):
        libc = ctypes.CDLL(None)
        os.close(libc.open(ctypes.c_char_p(os.fsencode(_mask())), 0))


class SocketCheat(Cheat):
    """Asks a server for ground truth (as a task on a running Ray cluster could): the server, in the test's
    process, sends the mask file's bytes to whoever connects."""

    name = "cheat-socket"

    def cheat(self):
        import socket

        with socket.create_connection(("127.0.0.1", int(os.environ["CHEAT_PORT"])), timeout=5) as s:
            s.recv(1 << 20)


class ViewCheat(Cheat):
    """Looks for ground truth next to the frames it was given (the unlabeled view)."""

    name = "cheat-view"

    def fit(self, train_videos):
        os.listdir(Path(train_videos[0].root) / "videos" / VIDEO / "mask_inst")


class ForkedWorkerCheat(Cheat):
    """Reads in a forked pool worker: the worker inherits the guard."""

    name = "cheat-forked-worker"

    def cheat(self):
        with concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("fork")) as pool:
            pool.submit(read_inst, _mask()).result()


CHEATS = [ForkedWorkerCheat, ThreadCheat, CatchCheat, ImportTimeCheat, InitCheat, EarlyImreadCheat, VideoCaptureCheat, EmptyCaptureCheat,
          Open3dCheat, ProcRootCheat, DirFdCheat, SubprocessCheat, SpawnCheat, CtypesCheat, SocketCheat, ViewCheat]


def _serve_once(payload: bytes) -> int:
    """A localhost TCP server (daemon thread) sending ``payload`` to its first client; returns its port."""
    import socket
    import threading

    server = socket.create_server(("127.0.0.1", 0))

    def serve():
        server.settimeout(60)
        with server:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            with conn:
                conn.sendall(payload)

    threading.Thread(target=serve, daemon=True).start()
    return server.getsockname()[1]


@pytest.fixture
def linked_dataset(analytic_dataset, tmp_path):
    """The dataset reached through a symlink (the old guard compared paths, not files)."""
    link = tmp_path / "link"
    link.symlink_to(analytic_dataset)
    return link


@pytest.mark.slow
@pytest.mark.parametrize("cheat", CHEATS, ids=lambda c: c.name)
def test_cheat_is_detected_and_not_scored(linked_dataset, tmp_path, monkeypatch, cheat):
    monkeypatch.setenv("CHEAT_ROOT", str(linked_dataset))
    if cheat is ImportTimeCheat:
        monkeypatch.setenv("CHEAT_AT_IMPORT", "1")
    if cheat is SocketCheat:
        monkeypatch.setenv("CHEAT_PORT", str(_serve_once(Path(_mask()).read_bytes())))
    out = tmp_path / "out"
    with pytest.raises(GroundTruthAccessError):
        run_fold(cheat, None, Dataset(linked_dataset), 0, out, FAST, progress=False)
    assert not (out / "scores").exists()
    rejected = read_json(next((out / "rejected").glob("*/*/fold0.json")))
    assert rejected["ground_truth_attempts"] and rejected["name"] == cheat.name


class StackCheat(Method):
    """Walks the call stack for the evaluator's ground truth; uses it if found."""

    name = "cheat-stack"

    def segment(self, video, frame_id, fg_mask):
        for info in inspect.stack():
            for value in info.frame.f_locals.values():
                if isinstance(value, dict) and (video.video_id, frame_id) in value:
                    return np.asarray(value[video.video_id, frame_id]).astype(np.uint16)
        return np.zeros_like(fg_mask, dtype=np.uint16)


def test_evaluator_memory_is_out_of_reach(analytic_dataset, tmp_path):
    rec = run_fold(StackCheat, None, Dataset(analytic_dataset), 0, tmp_path, FAST, progress=False)
    assert rec["metrics"]["IoU"] == 0.0 and rec["ground_truth_attempts"] == []


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
    """A method with a default process pool (forked workers, as ``ours`` matches scene pairs): allowed."""

    name = "pool-user"

    def fit(self, train_videos):
        with concurrent.futures.ProcessPoolExecutor(2) as pool:
            assert list(pool.map(_square, [1, 2, 3])) == [1, 4, 9]

    def segment(self, video, frame_id, fg_mask):
        return fg_mask.astype(np.uint16)


def test_forked_worker_pools_still_work(analytic_dataset, tmp_path):
    rec = run_fold(PoolUser, None, Dataset(analytic_dataset), 0, tmp_path, FAST, progress=False)
    assert rec["metrics"]["n_frames"] > 0 and rec["ground_truth_attempts"] == []
