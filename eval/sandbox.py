"""The wall between a method and ground truth: the method's process runs in a bubblewrap sandbox.

``evaluate`` never imports a method's code. It starts the method's own process, once to describe it (import
the class, resolve its config: :func:`describe_method`) and once per fold (``fit`` and ``segment``:
:func:`selfseg.eval.protocol.run_fold`), with `bubblewrap <https://github.com/containers/bubblewrap>`_
(``bwrap``, Debian package ``bubblewrap``) building a new mount, PID, network, IPC and UTS namespace for it:

* a new root holding only what is bound into it, at the same paths as outside: the system (``/usr``,
  ``/etc``, the ``/bin`` ``/lib`` links), the Python interpreter and the virtual environment, selfseg's
  source folders and a user method's own package, all **read-only**; the fold's inputs (see
  :func:`selfseg.eval.mounts.fold_mounts`), read-only; its work folders and its predictions folder, writable.
  Nothing else exists there: not the dataset's folder, not ``--out``, not other runs, not ``$HOME`` (``HOME``,
  ``MPLCONFIGDIR`` and ``TMPDIR`` point into a private, empty tmpfs ``/tmp``);
* its own PID namespace with a fresh ``/proc`` (no other process is visible), ``--die-with-parent`` and
  ``--new-session``; no network (only its own loopback); its own ``/dev`` (the NVIDIA devices bound in
  when present);
* inside it a method may do anything: threads, process pools, programs, ctypes.

The evaluator sends the job on the process's stdin (pickled: the child trusts the parent) and reads one JSON
reply from its stdout (never a pickle: the parent does not trust the child) once the sandbox's whole
process tree has exited (the kernel ends every process of a PID namespace when its first one exits). The
in-process check of :mod:`selfseg.guard` runs inside too, as a second line that names honest mistakes.

Where no sandbox can be started (no user namespaces, no ``bwrap``), :func:`sandbox_unavailable` says why:
``evaluate`` then runs built-in methods in a plain child process with the in-process check only, and a
user's method only with ``--trust-method``; their results are marked ``"isolation": "unsandboxed"``.
The environment variable ``SELFSEG_BWRAP`` names the ``bwrap`` binary (default: ``bwrap`` on ``PATH``).
"""
from __future__ import annotations

import contextlib
import functools
import importlib
import importlib.machinery
import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import threading
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

BWRAP_ENV = "SELFSEG_BWRAP"  # the bubblewrap binary; default: bwrap on PATH
SYSTEM_PATHS = ("/usr", "/etc", "/bin", "/sbin", "/lib", "/lib32", "/lib64", "/libx32")  # bound read-only (or linked)
SANDBOX_HOME = "/tmp/home"  # HOME inside: an empty folder of the private tmpfs /tmp
SANDBOX_MPLCONFIGDIR = "/tmp/matplotlib"
REPLY_LIMIT_BYTES = 16 << 20  # a longer reply is refused (the child is not trusted)
ISOLATION = ("sandbox", "unsandboxed")  # a result's "isolation"
GROUND_TRUTH = ("none", "train", "all")  # labels a method is given: none, the fold's training videos', all videos'
_CHILD = "from selfseg.eval.sandbox import child_main; child_main()"
_probed: dict[str, str | None] = {}


class SandboxError(ValueError):
    """No sandbox where one is required, or a folder it would mount holds the dataset or the results."""


class MethodProcessError(RuntimeError):
    """A method's process failed without an error the evaluator reports as bad input."""


@dataclass(frozen=True)
class MethodRef:
    """A method as ``evaluate`` runs it, without its code: the ``module:Class`` its process imports, the name
    its results are filed under, and what its sandbox holds besides the fold's unlabeled videos."""

    spec: str  # a registered name, or "package.module:ClassName"
    name: str  # the class's ``name``
    ground_truth: str = "none"  # labels the registry gives it (GROUND_TRUTH); a user's method: "none"
    config_dirs: tuple[tuple[str, str], ...] = ()  # (config field naming a folder, "ro" | "rw"): registry only
    code: tuple[str, ...] = ()  # a user's package folders (or module file), mounted read-only
    sys_path: tuple[str, ...] = ()  # the folders they are imported from
    sandboxed: bool = True  # False: a plain child process (no sandbox could be started here)

    @property
    def isolation(self) -> str:
        return ISOLATION[0] if self.sandboxed else ISOLATION[1]

    @property
    def user(self) -> bool:
        """A method outside the registry (``package.module:ClassName``)."""
        return ":" in self.spec

    @classmethod
    def of_class(cls, method_cls: type) -> MethodRef:
        """A Method subclass this process has already imported (Python API, tests): run by its import path,
        as a registered method if it is one, else as a user's method; sandboxed where a sandbox can start."""
        from selfseg.registry import METHODS

        spec = f"{method_cls.__module__}:{method_cls.__qualname__}"
        registered = METHODS.get(method_cls.name) == spec
        return _ref(method_cls.name if registered else spec, method_cls.name, sandbox_unavailable() is None)


def _ref(spec: str, name: str | None, sandboxed: bool) -> MethodRef:
    """The MethodRef of a registered name or a user's ``spec`` whose class is named ``name`` (checked; None:
    not known yet, while describing it)."""
    from selfseg.registry import CONFIG_DIRS, GROUND_TRUTH as REGISTERED_GT, check_user_method_name, split_spec

    if ":" not in spec:
        return MethodRef(spec, spec, REGISTERED_GT.get(spec, "none"), tuple(CONFIG_DIRS.get(spec, {}).items()),
                         sandboxed=sandboxed)
    attr = split_spec(spec)[1]
    code, sys_path = user_code(spec)
    name = attr if name is None else check_user_method_name(spec, name)
    return MethodRef(spec, name, code=code, sys_path=sys_path, sandboxed=sandboxed)


# ---- where a sandbox can run -------------------------------------------------------------------
def bwrap_binary() -> str:
    return os.environ.get(BWRAP_ENV) or shutil.which("bwrap") or "bwrap"


def sandbox_unavailable() -> str | None:
    """None if a trivial sandbox (the interpreter, doing nothing) starts here, else why not, in one line.
    Tried once per process and ``bwrap`` binary."""
    exe = bwrap_binary()
    if exe not in _probed:
        argv = bwrap_argv(exe, base_mounts(), os.getcwd()) + [sys.executable, "-I", "-S", "-c", "pass"]
        try:
            done = subprocess.run(argv, capture_output=True, text=True, timeout=60, env=_sandbox_env())
            lines = done.stderr.strip().splitlines()
            _probed[exe] = None if done.returncode == 0 else (lines[-1] if lines else f"exit code {done.returncode}")
        except (OSError, subprocess.TimeoutExpired) as e:
            _probed[exe] = f"{exe}: {getattr(e, 'strerror', None) or e}"
    return _probed[exe]


# ---- what is mounted ------------------------------------------------------------------------------
@dataclass(frozen=True)
class Mount:
    """``src`` (a folder or file outside) bound at ``dest`` inside; read-only unless ``writable``."""

    src: str
    dest: str
    writable: bool = False

    @classmethod
    def same(cls, path: str | os.PathLike, writable: bool = False) -> Mount:
        p = os.path.abspath(path)
        return cls(p, p, writable)


def _selfseg_source() -> list[str]:
    """selfseg's package folders when installed editable from a source tree outside the environment (each
    top-level folder of that tree that is a package: selfseg/, eval/, method/, ...), else none."""
    import selfseg

    tree = Path(selfseg.__file__).resolve().parents[1]
    if tree.is_relative_to(Path(sys.prefix).resolve()):
        return []
    return sorted(str(p) for p in tree.iterdir() if (p / "__init__.py").is_file())


@functools.cache
def base_mounts() -> tuple[Mount, ...]:
    """What every method's sandbox holds: the system, the interpreter, the virtual environment and selfseg's
    source, read-only."""
    paths = [p for p in SYSTEM_PATHS if os.path.lexists(p)] + [sys.base_prefix, sys.prefix] + _selfseg_source()
    kept: list[str] = []
    for p in paths:  # an interpreter under /usr is already there
        if not any(Path(p).is_relative_to(k) and not os.path.islink(k) for k in kept):
            kept.append(p)
    return tuple(Mount.same(p) for p in kept)


def user_code(spec: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(folders or file to mount, their sys.path folders) of the top-level package of ``spec``'s module,
    found on sys.path without importing anything; none if it is part of the environment or of selfseg.
    UnknownMethodError (one line) if it is not there."""
    from selfseg.registry import UnknownMethodError

    top = spec.partition(":")[0].split(".")[0]
    found = importlib.machinery.PathFinder.find_spec(top, sys.path) if top else None
    if found is None:
        raise UnknownMethodError(f"method {spec!r}: cannot import module {top!r} (is it on PYTHONPATH?)")
    places = list(found.submodule_search_locations or []) or [found.origin]
    covered = [Path(m.src) for m in base_mounts()]
    code = [os.path.abspath(p) for p in places if not any(Path(p).resolve().is_relative_to(c.resolve()) for c in covered)]
    return tuple(code), tuple(sorted({os.path.dirname(p) for p in code}))


def check_mounts(mounts: list[Mount], holds: list[str | os.PathLike], inside: list[str | os.PathLike]) -> None:
    """SandboxError (one line) if a mounted folder holds one of the ``holds`` folders or lies inside one of the
    ``inside`` folders (the dataset, the results)."""
    for m in mounts:
        src = Path(m.src).resolve()
        for f in map(Path, holds):
            if f.resolve().is_relative_to(src):
                raise SandboxError(f"{m.src}: a method's sandbox would mount this folder, which holds {f}; keep "
                                   "datasets, results and code in separate folders")
        for f in map(Path, inside):
            if src.is_relative_to(f.resolve()):
                raise SandboxError(f"{m.src}: a method's sandbox would mount this folder, which lies inside {f}; keep "
                                   "datasets, results and code in separate folders")


def bwrap_argv(exe: str, mounts: list[Mount], cwd: str) -> list[str]:
    """The ``bwrap`` command line (binary ``exe``) of a sandbox holding ``mounts`` (system links recreated as
    links), started in ``cwd`` (an empty folder there unless a mount holds it); the command follows.

    The command is the PID namespace's process 1 (``--as-pid-1``): bwrap's own init would reap it, and its
    CPU time and peak memory would then never reach the caller's ``RUSAGE_CHILDREN`` (what a benchmark's
    steps record). When it exits, the kernel kills whatever else is left in the namespace, as before."""
    argv = [exe, "--unshare-all", "--as-pid-1", "--die-with-parent", "--new-session", "--proc", "/proc", "--dev", "/dev",
            "--tmpfs", "/tmp", "--dir", SANDBOX_HOME, "--dir", SANDBOX_MPLCONFIGDIR]
    for dev in sorted(Path("/dev").glob("nvidia*")):  # CUDA, where there is a GPU
        argv += ["--dev-bind", str(dev), str(dev)]
    for m in mounts:
        if m.src == m.dest and os.path.islink(m.src) and m.src in SYSTEM_PATHS:  # /lib -> usr/lib
            argv += ["--symlink", os.readlink(m.src), m.dest]
        else:
            argv += ["--bind" if m.writable else "--ro-bind", m.src, m.dest]
    return argv + ["--dir", cwd, "--chdir", cwd, "--"]


def _sandbox_env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("XDG_")}
    return {**env, "HOME": SANDBOX_HOME, "MPLCONFIGDIR": SANDBOX_MPLCONFIGDIR, "TMPDIR": "/tmp"}


# ---- the method's process: parent side -----------------------------------------------------------
AUTOGROUP = "/proc/self/autogroup"  # Linux's scheduling group of a session: "/autogroup-N nice K"


def autogroup_nice() -> int | None:
    """The nice value of this process's scheduling autogroup (None where the kernel has no autogroups)."""
    try:
        return int(Path(AUTOGROUP).read_text().split()[-1])
    except (OSError, ValueError, IndexError):
        return None


@dataclass
class Job:
    """What a method's process is asked to do: import ``ref.spec``, then call ``entry`` ("module:function",
    selfseg's own) with the class and ``payload``; its dict return value is the reply."""

    ref: MethodRef
    entry: str
    payload: object
    guard: list[str] = field(default_factory=list)  # dataset paths whose ground truth selfseg.guard refuses
    # The caller's: the method's process runs in a session of its own, which the kernel gives a new autogroup at
    # nice 0, so without it a `nice`d evaluation's method would compete at full weight with everything else.
    autogroup_nice: int | None = field(default_factory=autogroup_nice)


def run_method_process(job: Job, mounts: list[Mount], forbidden: list[str | os.PathLike]) -> dict:
    """Run ``job`` in the method's process (its sandbox, unless ``job.ref.sandboxed`` is False: then a plain
    child) and return its reply (a dict) once its whole process tree has exited. ``mounts``: the job's inputs
    and outputs besides :func:`base_mounts` and the method's own code, which are checked not to hold or lie
    inside ``forbidden`` folders (SandboxError; the caller checks the mounts it chose). MethodProcessError if
    the process ended without a reply."""
    argv = [sys.executable, "-P", "-c", _CHILD]
    env = None
    if job.ref.sandboxed:
        code = [*base_mounts(), *(Mount.same(p) for p in job.ref.code)]
        check_mounts(code, forbidden, forbidden)
        argv = bwrap_argv(bwrap_binary(), code + list(mounts), os.getcwd()) + argv
        env = _sandbox_env()
    data = pickle.dumps(job)
    proc = None
    reply: list[bytes] = []
    try:
        with _ctrl_c_deferred():  # a started process is never left behind unattended
            proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env,
                                    start_new_session=True)
        reader = threading.Thread(target=_read_reply, args=(proc, reply), daemon=True)
        reader.start()
        try:
            proc.stdin.write(data)
            proc.stdin.close()
        except BrokenPipeError:  # it died before reading its job: reported below
            pass
        code_ = proc.wait()
        reader.join(None if job.ref.sandboxed else 1.0)  # unsandboxed: a forked leftover may hold the pipe
    except BaseException:
        if proc is not None:
            _kill(proc)
        raise
    text = b"".join(reply)
    if len(text) > REPLY_LIMIT_BYTES:
        raise MethodProcessError(f"method {job.ref.name!r}: its process replied with more than "
                                 f"{REPLY_LIMIT_BYTES} bytes")
    try:
        answer = json.loads(text)
    except ValueError:
        answer = None
    if not isinstance(answer, dict):
        where = "its sandbox" if job.ref.sandboxed else "its process"
        raise MethodProcessError(f"method {job.ref.name!r}: {where} exited with code {code_} without a reply "
                                 "(its messages are above)")
    return answer


@contextlib.contextmanager
def _ctrl_c_deferred() -> Iterator[None]:
    """Within the block (main thread only), Ctrl-C is held back and delivered when it ends."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught:
            signal.raise_signal(signal.SIGINT)


def _read_reply(proc: subprocess.Popen, out: list[bytes]) -> None:
    size = 0
    while chunk := proc.stdout.read1(1 << 16):
        out.append(chunk)
        size += len(chunk)
        if size > REPLY_LIMIT_BYTES:
            _kill(proc)
            break


def _kill(proc: subprocess.Popen) -> None:
    """End a method's process: its session (bwrap; the sandbox dies with it, --die-with-parent)."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()


def raise_reply_error(reply: dict, name: str, known: tuple[type[BaseException], ...],
                      paths: tuple[str, str] | None = None) -> None:
    """Raise the error a method's process reported, as the first of ``known`` it is an instance of (by class
    name: nothing from the child is unpickled), its message with ``paths[0]`` written as ``paths[1]``; else
    MethodProcessError with its traceback. Does nothing if it reported none."""
    error = reply.get("error")
    if not isinstance(error, dict):
        return
    kinds, message = error.get("kinds") or [], str(error.get("message", ""))
    if paths:
        message = message.replace(*paths)
    for cls in known:
        if cls.__name__ in kinds:
            raise cls(message)
    raise MethodProcessError(f"method {name!r} failed with {kinds[:1]} in its process:\n{error.get('traceback', '')}")


# ---- the method's process: child side ------------------------------------------------------------
def child_main() -> None:
    """Body of a method's process: read the Job from stdin, keep stdout for the reply (the method's own
    prints go to stderr), import the class under the in-process check, run the job, reply, exit."""
    from selfseg.guard import ground_truth_attempts, ground_truth_forbidden
    from selfseg.registry import METHODS, import_method

    job: Job = pickle.load(sys.stdin.buffer)
    if job.autogroup_nice:  # the caller's priority (lowering a nice needs a privilege: then it stays 0)
        with contextlib.suppress(OSError):
            Path(AUTOGROUP).write_text(str(job.autogroup_nice))
    reply_fd = os.dup(1)
    os.dup2(2, 1)
    os.dup2(os.open(os.devnull, os.O_RDONLY), 0)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C: the evaluator ends this process
    import multiprocessing

    multiprocessing.current_process().name = f"selfseg-{job.ref.name}"
    sys.path[:0] = job.ref.sys_path
    try:
        with ground_truth_forbidden(*job.guard) if job.guard else contextlib.nullcontext():
            method_cls = import_method(METHODS.get(job.ref.spec, job.ref.spec))
            module, _, function = job.entry.partition(":")
            reply = getattr(importlib.import_module(module), function)(method_cls, job.payload)
    except BaseException as e:  # noqa: BLE001 (reported to the evaluator)
        reply = {"error": {"kinds": [c.__name__ for c in type(e).__mro__], "message": str(e),
                           "traceback": traceback.format_exc()}}
    reply["ground_truth_attempts"] = list(ground_truth_attempts)
    sys.stderr.flush()
    data = json.dumps(reply, default=str).encode()
    while data:
        data = data[os.write(reply_fd, data):]
    os._exit(0)


# ---- describing a method -------------------------------------------------------------------------
def _describe(method_cls: type, payload: tuple) -> dict:
    """Child side of :func:`describe_method`: the class's name and its config resolved from a file and overrides."""
    from selfseg.config import load_config, to_dict

    config_path, overrides = payload
    return {"name": method_cls.name, "config": to_dict(load_config(method_cls.config_cls, config_path, overrides))}


def describe_method(spec: str, config_path: str | os.PathLike | None, overrides: list[str], sandboxed: bool,
                    dataset_root: str | os.PathLike, out: str | os.PathLike) -> tuple[MethodRef, dict]:
    """(the method, its resolved config as a dict) for ``evaluate --method spec``, asked of the method's own
    process (sandboxed unless ``sandboxed`` is False), where its module is imported under the in-process check
    of ``dataset_root``. Bad names, modules, classes or configs raise one-line errors (UnknownMethodError,
    ConfigError, ...); reaching for ground truth while importing raises GroundTruthAccessError."""
    from selfseg.config import ConfigError
    from selfseg.dataset import DatasetError
    from selfseg.fileio import FileFormatError
    from selfseg.guard import GroundTruthAccessError, guard_paths
    from selfseg.registry import METHODS, UnknownMethodError, get_method_class

    if ":" not in spec and spec not in METHODS:
        get_method_class(spec)  # the did-you-mean error
    mounts = [Mount.same(config_path)] if config_path is not None and Path(config_path).is_file() else []
    check_mounts(mounts, [dataset_root, out], [dataset_root, out])
    reply = run_method_process(Job(_ref(spec, None, sandboxed), f"{__name__}:_describe",
                                   (config_path, list(overrides)), guard_paths(dataset_root)),
                               mounts, [dataset_root, out])
    attempts = reply.get("ground_truth_attempts") or []
    if attempts:
        raise GroundTruthAccessError(f"while importing {spec!r}: {attempts[0]}")
    raise_reply_error(reply, spec, (UnknownMethodError, ConfigError, DatasetError, FileFormatError, FileNotFoundError))
    name = reply.get("name")
    if ":" not in spec and name != spec:
        raise UnknownMethodError(f"method {spec!r}: registered as {METHODS[spec]}, whose name is {name!r}")
    ref = _ref(spec, name, sandboxed)
    config = reply.get("config")
    if not isinstance(config, dict):
        raise MethodProcessError(f"method {spec!r}: its process described no config")
    return ref, config
