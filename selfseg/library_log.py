"""A run's library log: what libraries print (Open3D's Python module sends its C++ logger's warnings to
``sys.stdout``, one line each) goes to a file of the run instead of the terminal, and is counted there.

A command opens the log of a run with :func:`run_log` (``evaluate``: one per fold, in the method's process;
``evaluate3d`` and ``train``: one per run); it names the file in ``SELFSEG_LIBRARY_LOG``, for this process and the
worker processes it starts. Code that calls such a library wraps the calls in :func:`captured`: within it,
``sys.stdout`` is that file (appended), so the library's lines land there while the rest of the run prints as
before. Without a run's log (a library call outside these commands), :func:`captured` changes nothing. At the end
the command prints :func:`summary`, one line counting the log's messages by kind; the log keeps them in full.
"""
from __future__ import annotations

import contextlib
import os
import re
import threading
from collections import Counter
from pathlib import Path
from typing import Iterator

LOG_ENV = "SELFSEG_LIBRARY_LOG"  # the log file of the run this process works for
_MESSAGE = re.compile(r"^\[(\w+) (\w+)\] (.*)$")  # "[Open3D WARNING] text"
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_redirect = threading.Lock()  # sys.stdout is the process's: one redirection at a time


@contextlib.contextmanager
def run_log(path: str | os.PathLike) -> Iterator[Path]:
    """Within the block, library output of this process (and of worker processes started in it) goes to ``path``,
    which starts empty."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("")
    previous = os.environ.get(LOG_ENV)
    os.environ[LOG_ENV] = str(path)
    try:
        yield path
    finally:
        if previous is None:
            os.environ.pop(LOG_ENV, None)
        else:
            os.environ[LOG_ENV] = previous


@contextlib.contextmanager
def captured() -> Iterator[None]:
    """Within the block, what is printed to ``sys.stdout`` is appended to the run's log, if there is one and this
    process can open it (a worker on another machine may not see the file: then nothing changes)."""
    path = os.environ.get(LOG_ENV)
    try:
        log = open(path, "a") if path else None
    except OSError:
        log = None
    if log is None:
        yield
        return
    with _redirect, log, contextlib.redirect_stdout(log):
        yield


def summary(path: str | os.PathLike) -> str | None:
    """One line counting the messages of a run's log by library, level and text (numbers written N), or None if it
    holds none, e.g. ``library log run/library.log: 312 × Open3D WARNING 'Too few correspondences (N) after mutual
    filter, fall back to original correspondences.'``."""
    path = Path(path)
    try:
        lines = [_ANSI.sub("", line).strip() for line in path.read_text(errors="replace").splitlines()]
    except FileNotFoundError:
        return None
    kinds = Counter()
    for line in filter(None, lines):
        m = _MESSAGE.match(line)
        kinds[(m[1], m[2], re.sub(r"\d+", "N", m[3])) if m else ("other", "output", "")] += 1
    if not kinds:
        return None
    return f"library log {path}: " + "; ".join(f"{n} × {lib} {level}" + (f" {text!r}" if text else "")
                                               for (lib, level, text), n in kinds.most_common())
