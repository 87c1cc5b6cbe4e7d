"""One executor interface for the project's fan-outs: local process pools or Ray tasks.

``make_executor("local", workers=N)`` is a :class:`concurrent.futures.ProcessPoolExecutor` (today's
behaviour; Ray is not imported). ``make_executor("ray", address=..., workers=N)`` runs each
submitted call as one Ray task that declares ``num_cpus`` (and ``num_gpus``) and is retried by Ray
(``max_retries``) when its worker process or node dies. Without ``address`` a local Ray instance
with ``workers`` CPUs is started and shut down on exit; ``"auto"`` or ``HOST:PORT`` joins a
running cluster (started with ``ray start``), which is left running.

On a cluster every folder a task writes must be on a shared filesystem: :func:`check_shared_folder`
has one task write a probe file there and the driver read it back.
"""
from __future__ import annotations

import argparse
import concurrent.futures as cf
import logging
import os
import pickle
import socket
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from selfseg.config import load_section

EXECUTORS = ("local", "ray")
PROBE_PREFIX = ".selfseg-probe-"
RAY_MAX_RETRIES = 3  # re-runs of a task whose worker process or node died (application errors are not retried)
CONNECT_TIMEOUT_S = 5.0  # an unreachable --ray-address fails after this, not after Ray's minutes of retries


class ExecutorError(ValueError):
    """Bad executor choice, unreachable cluster, or an output folder the workers cannot see."""


@dataclass
class ExecutorConfig:
    """Where a command's fan-outs run: the ``executor:`` section of its YAML config (not part of the method's
    config or hashes: results do not depend on it), overridden by the command-line flags."""

    kind: str = "local"  # local (process pools; no Ray) | ray
    ray_address: str | None = None  # None: start a private Ray instance with this machine's CPUs; auto | HOST:PORT
    ray_cpus_per_task: float = 1  # CPUs each Ray task reserves
    ray_gpus_per_task: float = 0  # GPUs each Ray task reserves (Cycles on GPU, network training)

    def __post_init__(self):
        if self.kind not in EXECUTORS:
            raise ValueError(f"kind must be one of {', '.join(EXECUTORS)}, got {self.kind!r}")

    @property
    def distributed(self) -> bool:
        """False for plain local runs (today's behaviour: nothing of Ray is imported)."""
        return self.kind != "local" or self.ray_address is not None


def add_executor_arguments(p: argparse.ArgumentParser, what: str) -> None:
    """``--executor``, ``--ray-address``, ``--ray-cpus-per-task``, ``--ray-gpus-per-task``; ``what`` says which
    work runs as tasks. Flags left out take the YAML config's ``executor:`` section, then the defaults."""
    p.add_argument("--executor", help=f"where {what} run: {' or '.join(EXECUTORS)} (default local; also the "
                   "YAML config's executor.kind)")
    p.add_argument("--ray-address", help="with --executor ray: 'auto' or HOST:PORT of a running cluster (default: "
                   "start a Ray instance with this machine's CPUs for the run); outputs must be on a shared filesystem")
    p.add_argument("--ray-cpus-per-task", type=float, help="CPUs each Ray task reserves (default 1)")
    p.add_argument("--ray-gpus-per-task", type=float, help="GPUs each Ray task reserves (default 0)")


def executor_config(args: argparse.Namespace, config_path: str | os.PathLike | None) -> ExecutorConfig:
    """The flags of :func:`add_executor_arguments` over the ``executor:`` section of ``config_path`` over the
    defaults. Raises ExecutorError for a bad kind or task size (ConfigError for a bad YAML section)."""
    cfg = load_section(ExecutorConfig, config_path, "executor")
    for flag, field in (("executor", "kind"), ("ray_address", "ray_address"),
                        ("ray_cpus_per_task", "ray_cpus_per_task"), ("ray_gpus_per_task", "ray_gpus_per_task")):
        if getattr(args, flag) is not None:
            setattr(cfg, field, getattr(args, flag))
    if cfg.kind not in EXECUTORS:
        raise ExecutorError(f"--executor must be one of {', '.join(EXECUTORS)}, got {cfg.kind!r}")
    if cfg.kind == "local" and cfg.ray_address is not None:
        raise ExecutorError("--ray-address needs --executor ray")
    if cfg.ray_cpus_per_task <= 0 or cfg.ray_gpus_per_task < 0:
        raise ExecutorError("--ray-cpus-per-task must be > 0 and --ray-gpus-per-task ≥ 0")
    return cfg


def _check_address(address: str) -> None:
    """Raise ExecutorError unless ``address`` is ``auto`` or a HOST:PORT that accepts a TCP connection."""
    if address == "auto":
        return
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ExecutorError(f"--ray-address must be 'auto' or HOST:PORT, got {address!r}")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as e:
        raise ExecutorError(f"--ray-address {address}: no Ray cluster reachable there ({e.strerror or e}); "
                            "start one with `ray start --head` or fix the address") from None


def _call(payload: bytes) -> bytes:
    """Body of every Ray task: one submitted call, pickled both ways so that arrays arrive as private, writeable
    copies, as with a process pool (Ray's own zero-copy arrays are read-only)."""
    fn, args, kwargs = pickle.loads(payload)
    return pickle.dumps(fn(*args, **kwargs), protocol=5)


def _not_auth_enabled_note(record: logging.LogRecord) -> bool:
    """Log filter: drop Ray's note that token authentication is on (the safe default), keep its other warnings."""
    return not record.getMessage().startswith("Token authentication is enabled for this Ray cluster")


class RayExecutor(cf.Executor):
    """A ``concurrent.futures.Executor`` whose calls run as Ray tasks (one task per ``submit``).

    Functions and arguments travel by pickle, so they must be importable module-level functions and
    plain data; results come back as ordinary futures, already running (``cancel`` is refused, as for a
    started process-pool task; ``shutdown(cancel_futures=True)`` cancels the Ray tasks). A task's
    exception is raised as the original exception. ``shutdown`` waits for outstanding tasks and
    disconnects; a Ray instance this executor started stops with it, a joined cluster keeps running."""

    def __init__(self, address: str | None = None, workers: int = 1, num_cpus: float = 1, num_gpus: float = 0,
                 max_retries: int = RAY_MAX_RETRIES, env_vars: dict[str, str] | None = None):
        if address is not None:
            _check_address(address)
        else:  # Ray reads this when imported: a private instance binds the loopback interface only
            os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
        import ray

        logging.getLogger("ray._private.authentication.authentication_token_setup").addFilter(_not_auth_enabled_note)
        self._ray = ray
        self._cloudpickle = ray.cloudpickle
        self._task = ray.remote(num_cpus=num_cpus, num_gpus=num_gpus, max_retries=max_retries)(_call)
        self._futures: list[tuple[Any, cf.Future]] = []
        quiet = {"include_dashboard": False, "log_to_driver": False, "logging_level": "ERROR",
                 "configure_logging": False}
        if env_vars:  # in the environment every worker process starts with, on every node
            quiet["runtime_env"] = {"env_vars": dict(env_vars)}
        try:
            if address is None:  # a private instance on this machine, on the loopback interface
                ray.init(num_cpus=workers, **quiet)
            else:  # `ray start` turns token authentication on: send this machine's token if it has one
                from ray._private.authentication.authentication_token_setup import \
                    maybe_enable_token_auth_if_token_available
                maybe_enable_token_auth_if_token_available(warn_if_disabled=False)
                ray.init(address=address, **quiet)
        except ConnectionError as e:
            raise ExecutorError(f"--ray-address {address}: {str(e).splitlines()[0]}") from None
        fits = [n for n in ray.nodes() if n["Alive"] and n["Resources"].get("CPU", 0) >= num_cpus
                and n["Resources"].get("GPU", 0) >= num_gpus]
        if not fits:  # Ray would wait for such a node forever
            where = f"cluster {address}" if address else f"local Ray instance (--workers {workers} CPUs)"
            ray.shutdown()
            raise ExecutorError(f"no node of the {where} has {num_cpus:g} CPUs and {num_gpus:g} GPUs for one task; "
                                "lower --ray-cpus-per-task / --ray-gpus-per-task")

    def submit(self, fn: Callable, /, *args, **kwargs) -> cf.Future:
        ref = self._task.remote(self._cloudpickle.dumps((fn, args, kwargs)))
        future = cf.Future()
        future.set_running_or_notify_cancel()

        def done(ray_future: cf.Future) -> None:
            try:
                future.set_result(pickle.loads(ray_future.result()))
            except self._ray.exceptions.RayTaskError as e:
                future.set_exception(e.cause if isinstance(e.cause, BaseException) else e)
            except BaseException as e:  # noqa: BLE001 (a lost object or a cancelled task)
                future.set_exception(e)

        ref.future().add_done_callback(done)
        self._futures.append((ref, future))
        return future

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        if cancel_futures:
            for ref, f in self._futures:
                if not f.done():
                    self._ray.cancel(ref)
        if wait:
            cf.wait([f for _, f in self._futures])
        self._futures = []
        if self._ray.is_initialized():
            self._ray.shutdown()


def make_executor(kind: str = "local", address: str | None = None, workers: int = 1, num_cpus: float = 1,
                  num_gpus: float = 0, mp_context=None, env_vars: dict[str, str] | None = None) -> cf.Executor:
    """The executor for a fan-out, to use as a context manager.

    ``local``: a ProcessPoolExecutor of ``workers`` processes (``mp_context``, e.g. spawn for bpy; the
    platform default otherwise); ``address`` must be None. ``ray``: a :class:`RayExecutor`; ``workers``
    is the CPU count of the local instance it starts when ``address`` is None (a joined cluster has
    its own size); each task asks for ``num_cpus`` CPUs and ``num_gpus`` GPUs. ``env_vars`` (Ray only; a local
    pool inherits this process's environment) are set in every Ray worker's environment when it starts.
    Raises ExecutorError for an unknown kind, an unreachable address or bad counts."""
    if kind not in EXECUTORS:
        raise ExecutorError(f"--executor must be one of {', '.join(EXECUTORS)}, got {kind!r}")
    if workers < 1:
        raise ExecutorError(f"workers must be at least 1, got {workers}")
    if kind == "local":
        if address is not None:
            raise ExecutorError("--ray-address needs --executor ray")
        return cf.ProcessPoolExecutor(max_workers=workers, mp_context=mp_context)
    return RayExecutor(address, workers, num_cpus, num_gpus, env_vars=env_vars)


def shared_executor(where: ExecutorConfig, out: str | os.PathLike) -> cf.Executor:
    """The executor ``where`` names (a Ray instance it starts gets this machine's CPUs), once a task of it has
    written into ``out`` (created here) and this machine has read that back; the caller shuts it down."""
    ex = make_executor(where.kind, where.ray_address, os.cpu_count() or 1, num_cpus=where.ray_cpus_per_task,
                       num_gpus=where.ray_gpus_per_task)
    try:
        Path(out).mkdir(parents=True, exist_ok=True)
        check_shared_folder(ex, out)
    except BaseException:
        ex.shutdown(wait=False, cancel_futures=True)
        raise
    return ex


def _write_probe(path: str, token: str) -> str:
    """Task body of the shared-folder probe: write ``token`` to ``path`` if its folder exists there (nothing is
    created); returns the worker's host name."""
    try:
        Path(path).write_text(token)
    except OSError:  # the folder does not exist on this worker's machine
        pass
    return socket.gethostname()


def check_shared_folder(executor: cf.Executor, folder: str | os.PathLike) -> None:
    """Have a task of ``executor`` write a probe file into the existing ``folder`` and read it here; raise
    ExecutorError naming the folder if it is not there (the folder is not shared with the workers). Removes the
    probe (a probe written to a worker's own, unshared disk stays there)."""
    folder = Path(folder).resolve()
    token = uuid.uuid4().hex
    probe = folder / f"{PROBE_PREFIX}{token}"
    host = executor.submit(_write_probe, str(probe), token).result()
    try:
        seen = probe.read_text() == token
    except OSError:
        seen = False
    finally:
        probe.unlink(missing_ok=True)
    if not seen:
        raise ExecutorError(f"{folder}: a Ray worker on {host} wrote a probe file there that this machine cannot "
                            "see; the output folder must be on a filesystem shared by every node")
