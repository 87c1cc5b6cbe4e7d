"""A dataset's content manifest: size and sha256 of every file, and the identity hash built on them.

``manifest.json`` (written by ``generate_scenes`` and ``import_videos``) lists every file of the dataset
folder except itself and hidden entries (names starting with ``.``: interrupted scenes, progress records,
temporary files) as ``{"path": [size in bytes, sha256]}``. The dataset's identity
(:func:`content_hash`, what results, stage caches and unlabeled views are keyed on) is the hash of the
files' current listing, so any changed frame changes it. Digests are reused while a file keeps its size,
mtime and inode (a per-dataset cache under ``$SELFSEG_CACHE/stat``, default ``~/.cache/selfseg``), so the
cheap check reads no file that did not change; :func:`verify` with ``full=True`` re-reads every byte.

This module knows files, not the dataset's layout: the identities that depend on which file is what (the
geometry hash without the CPU-dependent RGB frames, a video's content hash) are in :mod:`selfseg.dataset`.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

from selfseg.fileio import FileFormatError, hash_file, hash_json, read_json, write_json

MANIFEST = "manifest.json"
MANIFEST_FORMAT = "selfseg-manifest 1"


def _stat_cache_path(root: Path) -> Path:
    base = Path(os.environ.get("SELFSEG_CACHE", Path.home() / ".cache" / "selfseg"))
    return base / "stat" / f"{hashlib.sha256(str(root.resolve()).encode()).hexdigest()[:16]}.json"


def dataset_files(root: str | os.PathLike) -> list[str]:
    """The files a manifest covers: every file under ``root`` (``/``-separated, sorted) but the manifest
    and hidden entries."""
    root = Path(root)
    found = []
    for folder, dirs, files in os.walk(root):
        dirs[:] = [d for d in dirs if not d.startswith(".")]
        rel = Path(folder).relative_to(root)
        found += [(rel / f).as_posix() for f in files if not f.startswith(".") and (rel / f).as_posix() != MANIFEST]
    return sorted(found)


def scan(root: str | os.PathLike, full: bool = False, only: list[str] | None = None) -> dict[str, list]:
    """``{path: [size, sha256]}`` of the dataset's files now (or of the paths ``only``); unless ``full``,
    digests of files whose size, mtime and inode are unchanged since the last scan come from the stat cache."""
    root = Path(root)
    cache_path = _stat_cache_path(root)
    try:
        cache = read_json(cache_path)
    except (FileNotFoundError, FileFormatError, OSError):
        cache = {}
    if full:
        cache = {}
    files, new_cache = {}, dict(cache) if only is not None else {}
    for rel in dataset_files(root) if only is None else only:
        st = (root / rel).stat()
        key = [st.st_size, st.st_mtime_ns, st.st_ino]
        hit = cache.get(rel)
        digest = hit[3] if isinstance(hit, list) and len(hit) == 4 and hit[:3] == key else hash_file(root / rel, 64)
        files[rel] = [st.st_size, digest]
        new_cache[rel] = key + [digest]
    if new_cache != cache:
        try:
            write_json(cache_path, new_cache, indent=None)
        except OSError:  # a read-only home: the next scan hashes again, nothing else changes
            pass
    return files


def manifest_hash(files: dict[str, list]) -> str:
    """The identity of a file listing (16 hex digits)."""
    return hash_json(files, n=16)


def content_hash(root: str | os.PathLike) -> str:
    """The dataset's identity: :func:`manifest_hash` of its files as they are now (cheap scan)."""
    return manifest_hash(scan(root))


def write_manifest(root: str | os.PathLike) -> str:
    """Hash every file of the dataset (full read), write ``manifest.json`` atomically; returns its hash."""
    files = scan(root, full=True)
    digest = manifest_hash(files)
    write_json(Path(root) / MANIFEST, {"format": MANIFEST_FORMAT, "hash": digest, "files": files})
    return digest


def read_manifest(root: str | os.PathLike) -> dict:
    """The stored manifest; a missing or malformed one raises an error naming the file."""
    path = Path(root) / MANIFEST
    rec = read_json(path)
    if not isinstance(rec, dict) or rec.get("format") != MANIFEST_FORMAT or not isinstance(rec.get("files"), dict):
        raise FileFormatError(f"{path}: not a {MANIFEST_FORMAT} manifest")
    return rec


def differences(root: str | os.PathLike, full: bool = True) -> tuple[dict[str, list], dict[str, str]]:
    """The stored manifest's files and ``{path: problem}`` for every file that differs from it (``missing``,
    ``not in the manifest``, ``size differs from the manifest``, ``content differs from the manifest``);
    ``full`` re-reads every byte."""
    stored = read_manifest(root)["files"]
    now = scan(root, full=full)
    found = {p: "missing" for p in stored if p not in now}
    found |= {p: "not in the manifest" for p in now if p not in stored}
    found |= {p: f"{'size' if stored[p][0] != now[p][0] else 'content'} differs from the manifest"
              for p in stored if p in now and stored[p] != now[p]}
    return stored, dict(sorted(found.items()))


def verify(root: str | os.PathLike, full: bool = True) -> tuple[str, list[str]]:
    """The stored manifest's hash and the differences of the dataset from it (``path: problem`` lines,
    empty when the data is the manifest's); ``full`` re-reads every byte."""
    stored, found = differences(root, full)
    return manifest_hash(stored), [f"{p}: {k}" for p, k in found.items()]
