"""The meshcat server process of :class:`slamkit.viz.server.MeshcatServer` (run as a script, by path).

meshcat's ``ZMQWebSocketBridge`` with both sockets on 127.0.0.1 and ports chosen by the OS: the zmq REP
socket binds ``tcp://127.0.0.1:*``, the tornado web server ``127.0.0.1:0``. Prints ``zmq_url=...`` and
``web_url=...`` on stdout, then serves until terminated or until its parent process is gone (checked every
second, so a kernel killed with SIGKILL does not leave it holding its ports). Imports meshcat, tornado and
zmq only (not slamkit: starting it stays fast).
"""

from __future__ import annotations

import argparse
import os
import warnings

import tornado.httpserver
import tornado.ioloop
import tornado.netutil
import zmq

with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    from meshcat.servers.zmqserver import ZMQWebSocketBridge

HOST = "127.0.0.1"
"""The only address the server listens on."""


class LoopbackBridge(ZMQWebSocketBridge):
    """meshcat's bridge with both sockets on 127.0.0.1 and OS-chosen ports."""

    def setup_zmq(self, url):
        socket, stream, _ = super().setup_zmq(url)
        return socket, stream, socket.getsockopt_string(zmq.LAST_ENDPOINT)

    def make_app(self):
        app = super().make_app()

        def listen(port, **kwargs):
            sockets = tornado.netutil.bind_sockets(port, address=HOST)
            server = tornado.httpserver.HTTPServer(app, **kwargs)
            server.add_sockets(sockets)
            self.bound_port = sockets[0].getsockname()[1]
            return server

        app.listen = listen
        return app


def _serve(parent_pid: int | None) -> None:
    warnings.simplefilter("ignore", DeprecationWarning)
    bridge = LoopbackBridge(zmq_url=f"tcp://{HOST}:*", host=HOST, port=0)
    bridge.fileserver_port = bridge.bound_port
    bridge.web_url = f"http://{HOST}:{bridge.bound_port}/static/"
    print(f"zmq_url={bridge.zmq_url}", flush=True)
    print(f"web_url={bridge.web_url}", flush=True)
    if parent_pid:
        def check_parent():
            if os.getppid() != parent_pid:
                bridge.ioloop.stop()

        tornado.ioloop.PeriodicCallback(check_parent, 1000).start()
    try:
        bridge.run()
    except KeyboardInterrupt:
        pass


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="meshcat server on 127.0.0.1 (free ports)")
    parser.add_argument("--parent-pid", type=int, default=None,
                        help="exit when this process is no longer the parent")
    args = parser.parse_args(argv)
    _serve(args.parent_pid)


if __name__ == "__main__":
    main()
