"""``voxfusion serve`` as a child process on loopback: for benchmarks, tests and scripts that need a real
server they can stop (SIGINT, the clean path) or kill (SIGKILL, the crash path).

Example::

    with ServeProcess(Path("/tmp/vf-data"), "--max-sessions", "16", zenoh=True) as srv:
        client = Client(srv.url)               # HTTP on srv.port
        zclient = ZenohClient(connect=[srv.zenoh_endpoint])
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import TracebackType

import httpx

__all__ = ["ServeProcess", "ServerStartError", "free_port"]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (the OS picks it)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ServerStartError(RuntimeError):
    """The child exited, or did not answer ``/healthz`` in time; the message ends with its log's tail."""


class ServeProcess:
    """``voxfusion serve --host 127.0.0.1`` on a free port with ``data_dir``; returns once ``/healthz``
    answers (and reports the zenoh bridge running, when ``zenoh``).

    Args:
        data_dir: the server's data folder (its log is written beside it, ``server-<port>.log``).
        *args: more ``voxfusion serve`` options (``"--config", "cpu"``, ...).
        device: ``--device``.
        zenoh: start the zenoh bridge listening on ``tcp/127.0.0.1:<zenoh_port>`` (a free port).
        api_key: ``VOXFUSION_API_KEY`` of the child (``None``: none, whatever this process has).
        start_timeout_s: how long to wait for ``/healthz``.

    Raises:
        ServerStartError: the child exited or did not become healthy in time.
    """

    def __init__(self, data_dir: Path, *args: str, device: str = "cpu", zenoh: bool = False,
                 api_key: str | None = None, start_timeout_s: float = 120.0) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.zenoh_port = free_port() if zenoh else None
        self.log_path = Path(data_dir).parent / f"server-{self.port}.log"
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        env.pop("VOXFUSION_API_KEY", None)
        if api_key is not None:
            env["VOXFUSION_API_KEY"] = api_key
        zenoh_args = ["--zenoh-listen", self.zenoh_endpoint] if zenoh else ["--no-zenoh"]
        cmd = [sys.executable, "-m", "voxfusion.cli", "serve", "--host", "127.0.0.1", "--port", str(self.port),
               "--data-dir", str(data_dir), "--device", device, "--log-level", "warning", *zenoh_args, *args]
        self._log = open(self.log_path, "wb")  # noqa: SIM115 - closed in stop() / kill()
        self.proc = subprocess.Popen(cmd, env=env, stdout=self._log, stderr=subprocess.STDOUT)
        self.http = httpx.Client(base_url=self.url, timeout=120.0)
        try:
            self.health = self._wait_healthy(start_timeout_s)
        except BaseException:
            self.kill()
            raise

    @property
    def zenoh_endpoint(self) -> str:
        """``tcp/127.0.0.1:<zenoh_port>`` (only with ``zenoh=True``)."""
        if self.zenoh_port is None:
            raise ValueError("this server was started without zenoh")
        return f"tcp/127.0.0.1:{self.zenoh_port}"

    def _wait_healthy(self, timeout_s: float) -> dict:
        deadline = time.monotonic() + timeout_s
        while True:
            if self.proc.poll() is not None:
                raise ServerStartError(f"voxfusion serve exited with {self.proc.returncode}:\n{self.log_tail()}")
            try:
                r = self.http.get("/healthz", timeout=2)
                if r.status_code == 200 and (self.zenoh_port is None or r.json().get("zenoh")):
                    return r.json()
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise ServerStartError(f"voxfusion serve did not become healthy in {timeout_s:.0f} s:\n"
                                       f"{self.log_tail()}")
            time.sleep(0.1)

    def log_tail(self, chars: int = 3000) -> str:
        """The last ``chars`` characters of the child's log (stdout and stderr)."""
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")[-chars:]

    def stop(self, timeout_s: float = 60.0) -> int:
        """SIGINT (the server finishes open work and closes its store), SIGKILL after ``timeout_s``.

        Returns:
            the child's exit status.
        """
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._close()
        return self.proc.returncode

    def kill(self) -> None:
        """SIGKILL now: what a crash or power loss looks like to the server's data folder."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=30)
        self._close()

    def _close(self) -> None:
        self.http.close()
        self._log.close()

    def __enter__(self) -> ServeProcess:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()
