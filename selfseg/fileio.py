"""Atomic file writes, JSON helpers and content hashing shared by every stage.

Every file selfseg writes goes through these helpers, so an interrupted run never leaves a
half-written file behind: data goes to a temporary sibling first and is renamed into place.
:func:`exclusive_lock` keeps two processes from working on the same output at once.
"""
from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any, Iterator


class FileFormatError(ValueError):
    """A file exists but cannot be parsed; the message names the file and the problem."""


def _umask_mode(mode: int) -> int:
    """``mode`` filtered by the process umask (mkstemp/mkdtemp would otherwise leave 0600/0700)."""
    umask = os.umask(0)
    os.umask(umask)
    return mode & ~umask


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temporary file in the same folder, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, _umask_mode(0o666))
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def _json_default(obj: Any) -> Any:
    # numpy scalars and arrays without importing numpy at module import time
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def dumps_json(obj: Any, indent: int | None = 1) -> str:
    """Deterministic JSON (sorted keys) with numpy support."""
    return json.dumps(obj, indent=indent, sort_keys=True, default=_json_default)


def write_json(path: str | os.PathLike, obj: Any, indent: int | None = 1) -> None:
    """Atomically write ``obj`` as JSON with sorted keys."""
    atomic_write_text(path, dumps_json(obj, indent) + "\n")


def read_json(path: str | os.PathLike) -> Any:
    """Read a JSON file; a missing or malformed file raises an error naming it."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return json.loads(f.read().decode("utf-8"))
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise FileFormatError(f"{path}: not valid JSON ({e})") from None


class BusyError(RuntimeError):
    """Another process holds the lock on the work asked for."""


@contextlib.contextmanager
def exclusive_lock(path: str | os.PathLike, what: str, wait: bool = False) -> Iterator[None]:
    """Hold an advisory lock (``flock``) on ``path`` for the block, writing this process's pid into it. If another
    process (or another open of the file) holds it: raise :class:`BusyError` naming ``what`` and the holder's pid at
    once, or with ``wait``, say so on stderr and block until the holder is done. The kernel drops the lock when its
    holder exits, so a killed run leaves no stale lock."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            if not wait:
                raise BusyError(f"{what} is being run by process {holder} (lock {path}); wait for it to finish") \
                    from None
            print(f"{what} is being run by process {holder} (lock {path}); waiting for it", file=sys.stderr,
                  flush=True)
            fcntl.flock(fd, fcntl.LOCK_EX)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_dir(final: str | os.PathLike) -> Iterator[Path]:
    """Build a folder under a temporary name and rename it to ``final`` only on success.

    ``final`` must not exist yet. On an exception the temporary folder is removed, so a
    crashed or interrupted run leaves either the complete folder or nothing.
    """
    final = Path(final)
    if final.exists():
        raise FileExistsError(f"{final}: already exists")
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=final.parent, prefix=f".{final.name}.", suffix=".partial"))
    os.chmod(tmp, _umask_mode(0o777))
    try:
        yield tmp
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def hash_file(path: str | os.PathLike, n: int = 16) -> str:
    """Short sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()[:n]


def hash_json(obj: Any, n: int = 12) -> str:
    """Short sha256 of the canonical JSON of ``obj`` (sorted keys, no whitespace)."""
    return hashlib.sha256(dumps_json(obj, indent=None).encode()).hexdigest()[:n]
