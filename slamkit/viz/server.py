"""A meshcat server bound to 127.0.0.1 only, owned by the Python process that started it.

meshcat 0.3.2 starts its server (``python -m meshcat.servers.zmqserver``) with the web server listening on
every interface (tornado's ``app.listen(port)``) and gives no option to change it; ``Visualizer.close()``
raises AttributeError and a killed kernel leaves the server holding its ports. So this module runs the
same tornado/zmq bridge (meshcat's ``ZMQWebSocketBridge``) in a child process of its own:

- the zmq socket binds ``tcp://127.0.0.1:*`` and the web server ``127.0.0.1:0`` (free ports chosen by the
  OS, so several servers and other users' meshcat on 6000/7000 never collide);
- the child exits by itself when its parent process goes away (checked every second), which covers a
  kernel killed with SIGKILL;
- :meth:`MeshcatServer.close` (also run by a weakref finalizer when the object is collected and at
  interpreter exit) terminates the child and waits for it.

>>> server = MeshcatServer()            # doctest: +SKIP
>>> vis = server.visualizer()           # a meshcat.Visualizer talking to it
>>> server.web_url                      # 'http://127.0.0.1:41235/static/'
>>> server.close()
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
import time
import warnings
import weakref
from pathlib import Path

import zmq

from ..errors import SlamkitError
from ._meshcat_server import HOST

with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    from meshcat.visualizer import ViewerWindow, Visualizer

SERVER_SCRIPT = Path(__file__).with_name("_meshcat_server.py")
"""The server process's program (meshcat's tornado/zmq bridge on 127.0.0.1)."""


class ViewerError(SlamkitError):
    """The 3D viewer's server could not be started or stopped responding."""


def _stop_process(proc: subprocess.Popen, sockets: list) -> None:
    """Close the client sockets and end the server process (SIGTERM, then SIGKILL after 3 s)."""
    for s in sockets:
        with contextlib.suppress(Exception):
            s.close(linger=0)
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            proc.terminate()
        try:
            proc.wait(timeout=3)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
            proc.wait(timeout=3)
    for stream in (proc.stdout, proc.stderr):
        with contextlib.suppress(Exception):
            stream.close()


class MeshcatServer:
    """A loopback-only meshcat server process with its lifecycle tied to this object.

    ``timeout``: seconds to wait for the server to start and for each command's reply (a server that
    stopped answering raises :class:`ViewerError` instead of hanging the notebook).
    """

    def __init__(self, timeout: float = 30.0):
        self.timeout = float(timeout)
        # run by path (-P: its folder is not put on sys.path): the child imports meshcat, not slamkit
        cmd = [sys.executable, "-u", "-P", str(SERVER_SCRIPT), "--parent-pid", str(os.getpid())]
        env = dict(os.environ, PYTHONWARNINGS="ignore::DeprecationWarning")
        # a session of its own: an interrupt (SIGINT to the kernel's process group) must not kill the viewer
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                                     start_new_session=True)
        self._sockets: list = []
        self._finalizer = weakref.finalize(self, _stop_process, self.proc, self._sockets)
        try:
            self.zmq_url, self.web_url = self._read_urls()
        except BaseException:
            self.close()
            raise
        # drain the pipes so the child never blocks on a full one (it logs every websocket connection)
        for stream in (self.proc.stdout, self.proc.stderr):
            threading.Thread(target=_drain, args=(stream,), daemon=True).start()

    def _read_urls(self) -> tuple[str, str]:
        urls: dict[str, str] = {}
        deadline = time.monotonic() + self.timeout
        lines: list[str] = []
        out = self.proc.stdout
        os.set_blocking(out.fileno(), False)
        buf = b""
        while len(urls) < 2:
            if time.monotonic() > deadline:
                raise ViewerError(f"meshcat server did not start within {self.timeout:.0f} s: {lines}")
            if self.proc.poll() is not None:
                err = self.proc.stderr.read().decode(errors="replace")
                raise ViewerError(f"meshcat server exited with code {self.proc.returncode}: {err.strip()}")
            chunk = out.read()
            if not chunk:
                time.sleep(0.02)
                continue
            buf += chunk
            *done, buf = buf.split(b"\n")
            for raw in done:
                line = raw.decode(errors="replace").strip()
                lines.append(line)
                key, _, value = line.partition("=")
                if key in ("zmq_url", "web_url"):
                    urls[key] = value
        os.set_blocking(out.fileno(), True)
        return urls["zmq_url"], urls["web_url"]

    # ------------------------------------------------------------------ state
    @property
    def pid(self) -> int:
        return self.proc.pid

    @property
    def alive(self) -> bool:
        return self.proc.poll() is None

    @property
    def ports(self) -> tuple[int, int]:
        """(zmq port, web port)."""
        return int(self.zmq_url.rsplit(":", 1)[1]), int(self.web_url.split(":")[2].split("/")[0])

    def __repr__(self) -> str:
        state = "running" if self.alive else "stopped"
        return f"MeshcatServer(pid={self.pid}, {self.web_url}, {state})"

    # ------------------------------------------------------------------ clients
    def visualizer(self):
        """A ``meshcat.Visualizer`` connected to this server (its own zmq socket, closed with the server)."""
        if not self.alive:
            raise ViewerError("the meshcat server is stopped")
        # ViewerWindow.__init__ would ask the server for its URL and print it; set it up directly
        window = ViewerWindow.__new__(ViewerWindow)
        window.server_proc = None
        window.zmq_url = self.zmq_url
        window.web_url = self.web_url
        window.zmq_socket = ViewerWindow.context.socket(zmq.REQ)
        window.zmq_socket.setsockopt(zmq.LINGER, 0)
        window.zmq_socket.setsockopt(zmq.RCVTIMEO, int(self.timeout * 1000))
        window.zmq_socket.setsockopt(zmq.SNDTIMEO, int(self.timeout * 1000))
        window.zmq_socket.connect(self.zmq_url)
        window.connect_zmq = lambda: None  # reconnecting would leak the configured socket
        self._sockets.append(window.zmq_socket)
        return Visualizer(window=window)

    def close(self) -> None:
        """Stop the server process (idempotent)."""
        self._finalizer()

    def __enter__(self) -> "MeshcatServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _drain(stream) -> None:
    with contextlib.suppress(Exception):
        for _ in iter(lambda: stream.read(4096), b""):
            pass
