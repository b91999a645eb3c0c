"""Dask executors of :func:`experiments.evaluation.run.evaluate`: a checked connection to an
existing scheduler, and a private local cluster (127.0.0.1 only, mutual TLS with a temporary
self-signed certificate, no HTTP server).
"""

from __future__ import annotations

import asyncio
import logging
import os
import shutil
import signal
import stat
import subprocess
import tempfile
import threading
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import distributed
from distributed.diagnostics.plugin import WorkerPlugin
from distributed.http.routing import RoutingApplication
from tornado.httpserver import HTTPServer

from lfm_env.validation import one_line


class _NoHttpServer:
    """Mixin: a Dask server whose HTTP application is built but never listens."""

    def start_http_server(
        self, routes: Any, dashboard_address: Any, default_port: int = 0, ssl_options: Any = None
    ) -> None:
        self.http_application = RoutingApplication(routes)
        self.http_server = HTTPServer(self.http_application)  # never bound to a port


class QuietScheduler(_NoHttpServer, distributed.Scheduler):
    """A Dask scheduler without any HTTP endpoint."""


class QuietWorker(_NoHttpServer, distributed.Worker):
    """A Dask worker without any HTTP endpoint that leaves Ctrl-C to the run's main process."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        super().__init__(*args, **kwargs)


class _NamedModules(WorkerPlugin):
    """Each worker of the cluster (also one started later in place of a dead one) finds the
    modules the run named in the working folder, and only those
    (:func:`lfm_env.working_folder.install`), before it unpickles a task."""

    name = "lfm-named-modules"

    def __init__(self, named: tuple) -> None:
        self.named = named

    def setup(self, worker: Any) -> None:
        from experiments.evaluation.pool import restore_environment
        from lfm_env import working_folder

        restore_environment()
        working_folder.install(self.named)


def find_named_modules(client: distributed.Client, named: tuple) -> None:
    """Give every worker of ``client``'s cluster the run's named modules (``named``:
    :func:`lfm_env.working_folder.state`)."""
    register = getattr(client, "register_plugin", None) or client.register_worker_plugin
    register(_NamedModules(named))


def check_scheduler(
    address: str, timeout: float, security: distributed.Security | None = None
) -> None:
    """Check that ``address`` answers Dask's ``identity`` request within ``timeout`` [s] (the
    client's own timeout bounds only the TCP connect).

    Raises:
        ConnectionError: one line naming the address, if nothing answers in time.
    """

    async def probe() -> Any:
        args = {} if security is None else security.get_connection_args("client")
        comm = await distributed.comm.connect(address, timeout=timeout, **args)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    try:
        reply = asyncio.run(asyncio.wait_for(probe(), timeout))
    except (asyncio.TimeoutError, TimeoutError) as exc:
        raise ConnectionError(
            f"Dask scheduler {address!r}: no answer as a Dask scheduler within {timeout:g} s"
        ) from exc
    except Exception as exc:
        raise ConnectionError(
            f"cannot reach the Dask scheduler at {address!r} within {timeout:g} s ({one_line(exc)})"
        ) from exc
    if not isinstance(reply, dict) or not str(reply.get("type", "")).endswith("Scheduler"):
        raise ConnectionError(f"{address!r} answers, but not as a Dask scheduler")


_KEY_FOLDER = "lfm-dask-"  # the temporary certificate folders: lfm-dask-<pid>-<random>
_KEY_FILES = {"key.pem", "cert.pem"}
_KEY_FOLDER_DAYS = 7  # the certificate's validity (openssl -days)


def remove_stale_key_folders() -> list[Path]:
    """Remove this user's certificate folders ``lfm-dask-<pid>-...`` of runs that ended without
    removing them (their process gone, or without a pid and older than 7 days), holding only
    the certificate and its key; returns them.
    """
    removed = []
    for folder in Path(tempfile.gettempdir()).glob(f"{_KEY_FOLDER}*"):
        try:
            st = folder.lstat()
            if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.geteuid():
                continue
            if not {p.name for p in folder.iterdir()} <= _KEY_FILES:
                continue
            pid = folder.name[len(_KEY_FOLDER) :].partition("-")[0]
            if pid.isdigit():
                if _alive(int(pid)):
                    continue
            elif time.time() - st.st_mtime < _KEY_FOLDER_DAYS * 86400:
                continue
            shutil.rmtree(folder)
            removed.append(folder)
        except OSError:
            continue  # (removed meanwhile, or not ours to read)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def temporary_security(stack: ExitStack) -> distributed.Security:
    """Dask TLS security from a new self-signed certificate (its own CA) in a private temporary
    folder (0700, removed when ``stack`` closes), by ``openssl`` or ``cryptography``.
    """
    try:
        return distributed.Security.temporary()  # needs the cryptography package
    except ImportError:
        pass
    openssl = shutil.which("openssl")
    if openssl is None:
        raise RuntimeError(
            "a local Dask cluster needs the 'openssl' command or the 'cryptography' package "
            "for its temporary TLS certificate"
        )
    remove_stale_key_folders()
    prefix = f"{_KEY_FOLDER}{os.getpid()}-"
    folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix=prefix)))
    key, cert = folder / "key.pem", folder / "cert.pem"
    subprocess.run(
        [openssl, "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1"]
        + ["-nodes", "-keyout", str(key), "-out", str(cert), "-days", "7"]
        + ["-subj", "/CN=lfm-evaluate"],
        check=True,
        capture_output=True,
        timeout=60,
    )
    pem = {"tls_ca_file": str(cert)}
    for who in ("client", "scheduler", "worker"):
        pem[f"tls_{who}_cert"] = str(cert)
        pem[f"tls_{who}_key"] = str(key)
    return distributed.Security(require_encryption=True, **pem)


def local_client(n_workers: int, stack: ExitStack) -> distributed.Client:
    """A client of a new private Dask cluster of ``n_workers`` single-threaded processes, closed
    when ``stack`` closes.
    """
    security = temporary_security(stack)
    common = {"host": "127.0.0.1", "protocol": "tls://", "security": security}
    scheduler = {
        "cls": QuietScheduler,
        "options": {**common, "dashboard_address": None, "dashboard": False},
    }
    worker = {
        "cls": distributed.Nanny,
        "options": {
            **common,
            "nthreads": 1,  # CasADi and the episode loop are single-threaded
            "worker_class": QuietWorker,
            "dashboard": False,
            # CRITICAL: a task's error reaches the run through its future; what the workers
            # log at ERROR is their lost connection when Ctrl-C closes the scheduler first
            # (a heartbeat's traceback on the user's terminal).
            "silence_logs": logging.CRITICAL,
        },
    }
    stack.callback(logging.disable, logging.NOTSET)  # runs last: logging back as it was
    cluster = stack.enter_context(
        distributed.SpecCluster(
            scheduler=scheduler,
            workers={i: worker for i in range(n_workers)},
            security=security,
            silence_logs=logging.CRITICAL,  # the scheduler's "Couldn't gather keys" at Ctrl-C
            name="lfm-evaluate",
        )
    )
    client = stack.enter_context(distributed.Client(cluster, security=security))
    stack.push(_quiet_when_interrupted)  # runs first, before the client and cluster close
    return client


def _quiet_when_interrupted(exc_type: type | None, *_: Any) -> bool:
    """On Ctrl-C, the closing cluster's messages about cancelled tasks and closed connections
    (logged with tracebacks by Dask) are not the user's business: logging is off until the
    cluster has closed."""
    if exc_type is not None and issubclass(exc_type, KeyboardInterrupt):
        logging.disable(logging.CRITICAL)
    return False
