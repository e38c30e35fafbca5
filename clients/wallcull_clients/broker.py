"""A NATS broker for load tests and tests: Debian's ``nats-server`` on a free loopback port.

A lab runs its own broker (or cluster); this one exists so that ``wallcull loadtest
--transport nats`` and the tests can measure and check the NATS path on one machine.
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import tempfile
import time


def find() -> str | None:
    """The ``nats-server`` executable, or None (``apt-get install nats-server``; Debian puts
    it in /usr/sbin, which a user's PATH may lack)."""
    return shutil.which("nats-server") or shutil.which("nats-server", path="/usr/sbin:/usr/bin")


class Broker:
    """``nats-server`` on a free loopback port until :meth:`stop` (or the ``with`` block)."""

    def __init__(self, port: int | None = None, user: str | None = None,
                 password: str | None = None):
        self.port = port or _free_port()
        self.auth = [] if user is None else ["--user", user, "--pass", password or ""]
        login = "" if user is None else f"{user}:{password or ''}@"
        self.url = f"nats://{login}127.0.0.1:{self.port}"
        self.proc = None
        self.log = tempfile.TemporaryFile()

    def start(self, timeout: float = 10.0) -> "Broker":
        server = find()
        if server is None:
            raise RuntimeError("no nats-server: install Debian's package (apt-get install "
                               "nats-server) or give a broker's URL")
        self.proc = subprocess.Popen([server, "-a", "127.0.0.1", "-p", str(self.port),
                                      *self.auth],
                                     stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout
        while True:
            if self.proc.poll() is not None:
                self.log.seek(0)
                raise RuntimeError(f"nats-server exited ({self.proc.returncode}): "
                                   f"{self.log.read().decode(errors='replace')[-1000:]}")
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                    return self
            except OSError:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"nats-server did not listen in {timeout:g} s") from None
                time.sleep(0.05)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()

    def __enter__(self) -> "Broker":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
