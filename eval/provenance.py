"""Where a result came from: the code (commit, dirty tree), the package versions, the machine, and the fields every
result record starts with (:func:`provenance`). The benchmarks record the same (``bench/common.py``)."""
from __future__ import annotations

import datetime
import functools
import importlib.metadata
import os
import platform
import subprocess
from pathlib import Path

from selfseg.config import config_hash, to_dict
from selfseg.dataset import FORMAT_VERSION, Dataset
from selfseg.eval.layout import SCHEMA_VERSION

VERSIONED_PACKAGES = ("selfseg", "numpy", "scipy", "torch", "open3d-cpu", "opencv-python-headless", "trimesh")


@functools.cache
def git_info() -> dict:
    """Commit of the selfseg checkout and whether tracked files differ from it, as this process first saw them
    (the code it loaded): the run functions ask before any work, so a commit made while a run trains does not
    relabel its results."""
    repo = Path(__file__).resolve().parents[1]
    try:
        commit = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10, check=True).stdout.strip() != ""
        return {"commit": commit, "dirty": dirty}
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}


def package_versions() -> dict:
    out = {}
    for pkg in VERSIONED_PACKAGES:
        try:
            out[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            out[pkg] = None
    return out


SPEED_FLAGS = ("avx2", "avx512f", "avx512_bf16", "amx_bf16")  # cpu_flags: what a machine record names


def _first_cpu(cpuinfo: Path) -> dict[str, str]:
    """The fields of ``cpuinfo``'s first processor (Linux /proc/cpuinfo; empty where there is none)."""
    fields = {}
    for ln in (cpuinfo.read_text().split("\n\n")[0].splitlines() if cpuinfo.is_file() else []):
        key, _, value = ln.partition(":")
        fields[key.strip()] = value.strip()
    return fields


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The CPU's model name with its family and model numbers (Linux: ``cpuinfo``'s first processor; "AMD EPYC,
    family 25 model 17"), else what ``platform`` reports. The numbers tell CPU types apart whose names do not (a
    virtual machine's Zen 4 and Zen 5 are both "AMD EPYC")."""
    fields = _first_cpu(cpuinfo)
    if "model name" not in fields:
        return platform.processor() or platform.machine()
    numbers = f", family {fields['cpu family']} model {fields['model']}" if "cpu family" in fields else ""
    return fields["model name"] + numbers


def cpu_flags() -> list[str]:
    """Which of the instruction sets that set the speed of training (:data:`SPEED_FLAGS`) the CPU has (Linux:
    /proc/cpuinfo; else empty). Without avx512_bf16 or amx_bf16, bf16 training is emulated and slow."""
    flags = _first_cpu(Path("/proc/cpuinfo")).get("flags", "").split()
    return [f for f in SPEED_FLAGS if f in flags]


def machine() -> dict:
    """The machine a measurement runs on, now: CPU model and its :func:`cpu_flags`, logical CPUs, load average
    (1, 5, 15 min; the cores may be shared), Python and platform."""
    return {"cpu": cpu_model(), "cpu_flags": cpu_flags(), "cpu_count": os.cpu_count(),
            "load_average": [round(x, 2) for x in os.getloadavg()], "python": platform.python_version(),
            "platform": platform.platform()}


def provenance(method: str, name: str, config, dataset: Dataset, task: str) -> dict:
    """The fields every result record starts with: schema, task ("2d" or "3d"), method, config, dataset, code, and
    the CPU (its model and :func:`cpu_flags`: they set what ``precision: auto`` trains in, and RGB renders differ
    between CPU types)."""
    return {
        "schema_version": SCHEMA_VERSION,
        "task": task,
        "name": name,
        "method": method,
        "config": to_dict(config),
        "config_hash": config_hash(config),
        "dataset": {"name": dataset.name, "root": str(dataset.root.resolve()),
                    "format_version": dataset.info.get("format_version", FORMAT_VERSION),
                    "content_hash": dataset.content_hash(), "n_videos": len(dataset.video_ids)},
        "git": dict(git_info()),
        "versions": package_versions(),
        "cpu": {"model": cpu_model(), "flags": cpu_flags()},  # RGB renders and learned runs differ by CPU type
        "created_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


def run_key(record: dict) -> dict:
    """What identifies the run a result record came from: method, config hash, dataset content and commit (what
    resuming and archiving compare; a record's time stamp and timings are not part of it)."""
    return {"method": record.get("method"), "config_hash": record.get("config_hash"),
            "dataset": record.get("dataset", {}).get("content_hash"), "commit": record.get("git", {}).get("commit")}
