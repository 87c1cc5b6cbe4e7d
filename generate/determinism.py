"""Cross-machine determinism of generation: pinned numerical libraries and snapped geometry.

Measured (tiny preset, physics only): on one x86-64 machine, which maths kernels the libraries pick at
run time changes the dataset.

* glibc's libm picks FMA variants of ``sin``, ``cos``, ``exp``, ... when the CPU has FMA and AVX2.
  Bullet calls them every step, so a machine without FMA (``GLIBC_TUNABLES=glibc.cpu.hwcaps=-FMA``)
  settles every tiny scene differently (objects up to 4.6 cm apart).
* OpenBLAS picks kernels per CPU (``OPENBLAS_CORETYPE``): 4×4 matrix products that build the lamp
  differ in the last bit, and the chaotic drop turns that into poses 15 cm apart.
* numpy dispatches its ufuncs to the CPU's SIMD extensions (SVML ``sin``/``cos`` on AVX-512 CPUs).

:func:`pinned_env` makes every x86-64 CPU take the baseline path of all three; the
``generate_scenes`` command runs itself under it (:func:`reexec_pinned`). :func:`snap` rounds
geometry (metres) and poses to a power-of-two grid, so last-bit noise left anywhere upstream
(another BLAS, another compiler) vanishes before physics and before anything is written.

Not pinned, because it cannot be: Cycles, Embree and OpenImageDenoise choose their SIMD kernels by CPUID,
so Cycles' RGB frames from CPUs of other types differ by 1 in a few 8-bit values per frame (measured: an
AMD Zen 4 against an Intel Xeon with AVX-512 FP16 and against the machine of the first published tiny
hash, PSNR 91–99 dB). Everything else, depth and masks included (Workbench), is the same bytes:
:func:`selfseg.dataset.geometry_hash` is that part's identity.
"""
from __future__ import annotations

import os
import sys

import numpy as np

# glibc.cpu.hwcaps entries that send libm to its baseline (SSE2) variants on every x86-64 CPU
_GLIBC_HWCAPS_OFF = ("-AVX2", "-FMA", "-FMA4")
# numpy's dispatched (non-baseline) x86 features (numpy 1.26); names a CPU lacks are ignored
_NPY_FEATURES_OFF = ("SSSE3 SSE41 POPCNT SSE42 AVX F16C XOP FMA4 FMA3 AVX2 AVX512F AVX512CD AVX512_KNL AVX512_KNM "
                     "AVX512_SKX AVX512_CLX AVX512_CNL AVX512_ICL AVX512_SPR")
PINNED = {"OPENBLAS_CORETYPE": "Prescott", "OPENBLAS_NUM_THREADS": "1", "NPY_DISABLE_CPU_FEATURES": _NPY_FEATURES_OFF}
GRID_BITS = 24  # snap(): metres to 2^-24 m ≈ 0.06 µm


def _glibc_tunables(current: str) -> str:
    """``current`` GLIBC_TUNABLES with the hwcaps of :data:`_GLIBC_HWCAPS_OFF` switched off too."""
    entries = [e for e in current.split(":") if e]
    hw = [e for e in entries if e.startswith("glibc.cpu.hwcaps=")]
    caps = hw[-1].split("=", 1)[1].split(",") if hw else []
    caps += [c for c in _GLIBC_HWCAPS_OFF if c not in caps]
    rest = [e for e in entries if not e.startswith("glibc.cpu.hwcaps=")]
    return ":".join(rest + ["glibc.cpu.hwcaps=" + ",".join(c for c in caps if c)])


def pinned_env(environ: dict[str, str]) -> dict[str, str]:
    """``environ`` with the numerical libraries pinned to their baseline x86-64 kernels."""
    return {**environ, **PINNED, "GLIBC_TUNABLES": _glibc_tunables(environ.get("GLIBC_TUNABLES", ""))}


def is_pinned(environ: dict[str, str]) -> bool:
    """Whether ``environ`` already is :func:`pinned_env` (glibc reads it only when a process starts)."""
    return pinned_env(environ) == dict(environ)


def start_environ() -> dict[str, str]:
    """The environment this process started with (what glibc read), not today's ``os.environ``: Linux's
    ``/proc/self/environ``, else ``os.environ``."""
    try:
        raw = open("/proc/self/environ", "rb").read()
    except OSError:
        return dict(os.environ)
    pairs = (e.split(b"=", 1) for e in raw.split(b"\0") if b"=" in e)
    return {k.decode(errors="surrogateescape"): v.decode(errors="surrogateescape") for k, v in pairs}


def pinned_vars(environ: dict[str, str]) -> dict[str, str]:
    """The variables :func:`pinned_env` sets, with their pinned values for ``environ``: what another process
    (a Ray worker on another machine) needs in its starting environment to compute as a pinned one does."""
    pinned = pinned_env(environ)
    return {k: pinned[k] for k in (*PINNED, "GLIBC_TUNABLES")}


def reexec_pinned(module: str) -> None:
    """Replace this process by ``python -m module ARGS`` under :func:`pinned_env`, unless already pinned."""
    if not is_pinned(os.environ):
        sys.stdout.flush()
        sys.stderr.flush()
        os.execve(sys.executable, [sys.executable, "-m", module, *sys.argv[1:]], pinned_env(dict(os.environ)))


def snap(a, bits: int = GRID_BITS) -> np.ndarray:
    """``a`` (float64) rounded to the grid 2^-bits: exact, identical on every IEEE machine."""
    scale = float(2 ** bits)
    return np.rint(np.asarray(a, dtype=np.float64) * scale) / scale


def snap_pose(T: np.ndarray) -> np.ndarray:
    """A 4×4 rigid transform (metres) with its rotation snapped to 2^-30 and its translation to 2^-24 m."""
    T = np.array(T, dtype=np.float64)
    T[:3, :3], T[:3, 3] = snap(T[:3, :3], 30), snap(T[:3, 3])
    return T
