"""The Dask executors (``experiments.evaluation.executors``): a scheduler address that is not
one fails within the timeout; the local cluster refuses foreign clients and serves no HTTP.
Real listening sockets and a real local cluster on loopback."""

from __future__ import annotations

import http.server
import os
import socket
import subprocess
import threading
from contextlib import ExitStack

import pytest

from experiments.evaluation import run as evaluation
from tests.experiments.evaluation.live_runs import ENV, LFM_EVALUATE


class _Silent(threading.Thread):
    """A listener that accepts connections and never answers."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.held: list[socket.socket] = []

    def run(self) -> None:
        while True:
            try:
                self.held.append(self.sock.accept()[0])
            except OSError:
                return


class _Http(http.server.BaseHTTPRequestHandler):
    def do_GET(self) -> None:  # noqa: N802 (http.server's name)
        self.send_response(200)
        self.end_headers()
        self.wfile.write(b"hello")

    def log_message(self, *args) -> None:
        pass


@pytest.mark.parametrize("kind", ["silent", "http"])
def test_a_scheduler_address_that_is_not_dask_fails_within_the_timeout(kind, tmp_path):
    """Case 2: a silent listener or an HTTP server given as --scheduler."""
    if kind == "silent":
        server = _Silent()
        server.start()
        port, stop = server.port, server.sock.close
    else:
        httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Http)
        threading.Thread(target=httpd.serve_forever, daemon=True).start()
        port, stop = httpd.server_address[1], httpd.shutdown
    address = f"tcp://127.0.0.1:{port}"
    try:
        proc = subprocess.run(
            [str(LFM_EVALUATE), "--no-report", "--quiet", "--agents", "nominal", "--seeds", "0"]
            + ["--scheduler", address, "--out", str(tmp_path / "out")],
            cwd=tmp_path,
            env=ENV,
            capture_output=True,
            text=True,
            timeout=60,  # generous: the stated timeout is 5 s
        )
    finally:
        stop()
    assert proc.returncode == 2, proc.stderr
    assert address in proc.stderr and "Dask scheduler" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "out").exists()


def test_local_dask_cluster_refuses_foreign_clients_and_serves_no_http(tmp_path):
    """Case 9: TLS with a temporary certificate, and no HTTP endpoint at all."""
    pytest.importorskip("distributed")
    psutil = pytest.importorskip("psutil")
    from experiments.evaluation import executors

    with ExitStack() as stack:
        client = evaluation._connect_dask(None, 1, stack)
        address = client.scheduler.address
        assert address.startswith("tls://127.0.0.1:")
        assert client.submit(os.getpid).result() != os.getpid()  # our own client works
        info = client.scheduler_info()["workers"]
        ports = {int(address.rsplit(":", 1)[1])}
        for w, d in info.items():
            ports |= {int(w.rsplit(":", 1)[1]), int(d["nanny"].rsplit(":", 1)[1])}
        procs = [psutil.Process(), *psutil.Process().children(recursive=True)]
        listening = {
            c.laddr.port
            for p in procs
            for c in p.net_connections(kind="inet")
            if c.status == psutil.CONN_LISTEN
        }
        assert listening == ports  # scheduler, worker, nanny: no dashboard, no /info page
        # Our own certificate is accepted; a foreign client is refused, without a
        # certificate, with a certificate of its own, over TLS or plain TCP.
        executors.check_scheduler(address, 10, client.security)
        plain = address.replace("tls://", "tcp://")
        for security in (None, executors.temporary_security(stack)):
            for addr in (address, plain):
                with pytest.raises(ConnectionError, match="Dask scheduler"):
                    executors.check_scheduler(addr, 10, security)


def test_the_key_of_a_killed_dask_run_is_removed_at_the_next_start(tmp_path, monkeypatch):
    """A SIGKILLed ``--dask-workers`` run left its temporary TLS key
    (``lfm-dask-*/key.pem``) in the temporary folder for ever. Now the next local cluster
    removes the folders of runs that no longer live (and only those, holding only the
    certificate and key)."""
    import signal
    import tempfile
    import time

    from experiments.evaluation.executors import temporary_security
    from tests.experiments.evaluation.live_runs import quick_yaml

    temp = tmp_path / "tmp"
    temp.mkdir()
    out = tmp_path / "out"
    config = quick_yaml(tmp_path, max_steps=60)
    cmd = [str(LFM_EVALUATE), "--config", str(config), "--agents", "nominal", "--seeds", "0:4"]
    cmd += ["--dask-workers", "1", "--out", str(out), "--no-report", "--quiet"]
    proc = subprocess.Popen(
        cmd, env={**ENV, "TMPDIR": str(temp)}, start_new_session=True,
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while not list(temp.glob("lfm-dask-*/key.pem")):
            assert proc.poll() is None, "the run ended before its cluster started"
            assert time.monotonic() < deadline, "no certificate folder appeared"
            time.sleep(0.05)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    (left,) = temp.glob("lfm-dask-*")
    assert (left / "key.pem").is_file()  # what the killed run leaves
    alive = temp / "lfm-dask-not-ours"
    alive.mkdir()
    (alive / "notes.txt").write_text("a folder of another program, left alone")
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    with ExitStack() as stack:
        temporary_security(stack)
        (mine,) = [p for p in temp.glob("lfm-dask-*") if p != alive]
        assert mine != left and (mine / "key.pem").is_file()
    assert not left.exists()
    assert (alive / "notes.txt").is_file()
    assert not mine.exists()
