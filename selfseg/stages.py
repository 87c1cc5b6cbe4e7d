"""Per-scene stage cache: pipeline stages exchange files, and a re-run reuses valid outputs.

Layout: ``CACHE/<stage>/<scene>/`` holds a stage's files for one scene plus ``stage.json``,
which records the stage's *key*: its config hash, the keys of the stages it read, the code
version and anything else that determines the output. A cached output is valid when its key
matches; otherwise it is rebuilt. Outputs are written into a temporary folder and renamed into
place, so an interrupted run leaves either a complete, valid stage or nothing.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import time
from pathlib import Path
from typing import Iterator

from selfseg.fileio import atomic_dir, hash_json, read_json, write_json

STAGE_FILE = "stage.json"


class StageCache:
    """Root folder of a pipeline run's per-scene stage outputs."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    def path(self, stage: str, scene: str) -> Path:
        return self.root / stage / scene

    def key_hash(self, stage: str, scene: str) -> str | None:
        """Hash of the key a completed stage output was built with, or None if absent."""
        meta = self.path(stage, scene) / STAGE_FILE
        return read_json(meta)["key_hash"] if meta.is_file() else None

    def is_valid(self, stage: str, scene: str, key: dict) -> bool:
        return self.key_hash(stage, scene) == hash_json(key)

    @contextlib.contextmanager
    def write(self, stage: str, scene: str, key: dict) -> Iterator[Path]:
        """Yield a temporary folder for the stage's files; on success it replaces any stale output.

        Safe with concurrent writers of the same stage (two runs sharing a cache): each stages in its own
        folder, and the first to finish wins; a later writer with the same key discards its output, so a
        valid stage never changes under a reader (stages need not be bit-reproducible).
        """
        final = self.path(stage, scene)
        start = time.perf_counter()
        staging = final.with_name(f"{final.name}.new-{os.getpid()}")
        shutil.rmtree(staging, ignore_errors=True)
        with atomic_dir(staging) as tmp:
            yield tmp
            write_json(tmp / STAGE_FILE, {"stage": stage, "scene": scene, "key": key, "key_hash": hash_json(key),
                                          "seconds": round(time.perf_counter() - start, 3)})
        if self.is_valid(stage, scene, key):  # another writer finished the same stage first
            shutil.rmtree(staging)
            return
        if final.exists():
            shutil.rmtree(final)
        staging.rename(final)
