"""The in-process ground-truth check: a cheap second line, never the wall.

The wall is ``evaluate``'s sandbox (:mod:`selfseg.eval.sandbox`): a method's process runs in its own mount
namespace, where ground truth it may not read does not exist. This module only names honest mistakes in
code that runs as the evaluator's own user: inside a block of :func:`ground_truth_forbidden`, opening,
listing, linking or copying a ground-truth file (``mask_inst/``, ``scene_gt.json``, ``scene_info.json``) of
the given dataset folders, by any path that resolves into them, raises :class:`GroundTruthAccessError` and is
recorded in :data:`ground_truth_attempts`. It sees Python's own file operations (``open``, ``os.open``,
``os.listdir``, numpy, json, PIL, this project's readers) and OpenCV's ``imread``; code that wants to get
round it can (ctypes, other programs, clearing this module's state), which is why it is not the wall.
Used by ``evaluate`` inside the method's process (sandboxed or not), ``evaluate3d``, ``train`` and the
pipeline's per-video tasks.
"""
from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path
from typing import Any, Iterator

from selfseg.dataset import GROUND_TRUTH_NAMES


class GroundTruthAccessError(PermissionError):
    """Raised when code running under :func:`ground_truth_forbidden` opens a ground-truth file."""


# Every refused access in this process, caught by the caller or not (evaluate reports them).
ground_truth_attempts: list[str] = []
_guard_roots: list[Path] = []  # guarded dataset folders (absolute and resolved paths), all threads
_hook_installed = False
_PATH_EVENTS = ("open", "os.listdir", "os.scandir", "os.link", "os.symlink", "os.rename", "shutil.copyfile",
                "shutil.copytree", "os.chdir")
_TWO_PATH_EVENTS = ("os.link", "os.symlink", "os.rename", "shutil.copyfile", "shutil.copytree")


def _is_ground_truth(path: str, roots: list[Path]) -> bool:
    for p in {Path(os.path.abspath(path)), Path(os.path.realpath(path))}:  # realpath: symlinks, /proc/self/root
        if not any(part in GROUND_TRUTH_NAMES for part in p.parts):
            continue
        for root in roots:
            try:
                rel = p.relative_to(root)
            except ValueError:
                continue
            if any(part in GROUND_TRUTH_NAMES for part in rel.parts):
                return True
    return False


def _check_path(path: Any) -> None:
    if _guard_roots and isinstance(path, (str, bytes, os.PathLike)):
        path = os.fsdecode(path)
        if _is_ground_truth(path, _guard_roots):
            ground_truth_attempts.append(path)
            raise GroundTruthAccessError(f"{path}: ground truth is off limits here (self-supervised path)")


def _audit(event: str, args: tuple) -> None:
    if event in _PATH_EVENTS and args:
        _check_path(args[0])
        if event in _TWO_PATH_EVENTS and len(args) > 1:
            _check_path(args[1])


def _guard_cv2_readers() -> None:
    """OpenCV reads files in C++, out of the audit hook's sight: check its readers' paths too."""
    import cv2

    for name in ("imread", "imreadmulti"):
        original = getattr(cv2, name, None)
        if original is None or getattr(original, "_selfseg_guarded", False):
            continue

        def guarded(filename, *args, _original=original, **kwargs):
            _check_path(filename)
            return _original(filename, *args, **kwargs)

        guarded._selfseg_guarded = True
        setattr(cv2, name, guarded)


def _install_hook() -> None:
    global _hook_installed
    if not _hook_installed:
        sys.addaudithook(_audit)
        _guard_cv2_readers()
        _hook_installed = True


def guard_paths(*dataset_roots: str | os.PathLike) -> list[str]:
    """The paths :func:`ground_truth_forbidden` compares against for ``dataset_roots``: each one absolute and
    resolved (computed where the folders exist, for a process that may not see them)."""
    return sorted({f(r) for r in dataset_roots for f in (os.path.abspath, os.path.realpath)})


@contextlib.contextmanager
def ground_truth_forbidden(*dataset_roots: str | os.PathLike) -> Iterator[None]:
    """Within this block, opening or listing ground truth under the given datasets raises, in every thread."""
    global _guard_roots
    _install_hook()
    previous = _guard_roots
    _guard_roots = previous + [Path(p) for p in guard_paths(*dataset_roots)]
    try:
        yield
    finally:
        _guard_roots = previous
