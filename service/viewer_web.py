"""``--rerun-web PORT``: the Rerun web viewer on 127.0.0.1, kept from reaching anything but this machine.

``rerun --serve-web`` (the executable that ships with rerun-sdk) serves the viewer's files and the gRPC server the
page reads the map from, both bound to 127.0.0.1 on ports of its own. The page itself would, in a browser with
internet, post usage events to Rerun and fetch fonts and release notes from other hosts; so objslam serves it
through a small proxy on ``PORT`` that adds a Content-Security-Policy allowing connections to this machine's
viewer servers only: the browser refuses every other request.
"""

from __future__ import annotations

import logging
import shutil
import subprocess
import threading
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from service.viewer_connect import ViewerError, free_port, rerun_executable, viewer_env, wait_listening

log = logging.getLogger(__name__)

HOP_BY_HOP = {"connection", "keep-alive", "transfer-encoding", "content-security-policy", "server", "date"}
DIRECT = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # never through an HTTP proxy


def content_policy(grpc_port: int) -> str:
    """What the page may load and connect to: itself and the gRPC server on this machine, nothing else."""
    grpc = f"http://127.0.0.1:{grpc_port} http://localhost:{grpc_port}"
    return (
        "default-src 'self'; script-src 'self' 'unsafe-inline' 'wasm-unsafe-eval'; style-src 'self' 'unsafe-inline'; "
        f"img-src 'self' data: blob:; font-src 'self' data:; worker-src 'self' blob:; connect-src 'self' {grpc}"
    )


class _Proxy(BaseHTTPRequestHandler):
    server: _ProxyServer

    def do_GET(self) -> None:
        upstream = f"http://127.0.0.1:{self.server.upstream_port}{self.path}"
        try:
            reply = DIRECT.open(upstream, timeout=30.0)
        except urllib.error.HTTPError as exc:
            reply = exc
        except OSError as exc:
            self.send_error(502, f"rerun web viewer: {exc}")
            return
        with reply:
            self.send_response(reply.status)
            for name, value in reply.headers.items():
                if name.lower() not in HOP_BY_HOP:
                    self.send_header(name, value)
            self.send_header("Content-Security-Policy", self.server.policy)
            self.end_headers()
            shutil.copyfileobj(reply, self.wfile, 1 << 20)

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("web viewer: " + format, *args)


class _ProxyServer(ThreadingHTTPServer):
    daemon_threads = True

    def __init__(self, port: int, upstream_port: int, policy: str):
        super().__init__(("127.0.0.1", port), _Proxy)
        self.upstream_port, self.policy = upstream_port, policy


@dataclass
class WebViewer:
    """The web viewer on 127.0.0.1:``port`` (through the proxy) and the gRPC server it reads from."""

    port: int
    memory_limit: str = "512MiB"
    grpc_port: int = field(default_factory=free_port)
    process: subprocess.Popen[bytes] | None = None
    proxy: _ProxyServer | None = None
    serving: threading.Thread | None = None

    @property
    def grpc_url(self) -> str:
        return f"rerun+http://127.0.0.1:{self.grpc_port}/proxy"

    @property
    def url(self) -> str:
        """The page to open: the web viewer, connected to its gRPC server."""
        return f"http://127.0.0.1:{self.port}/?url={self.grpc_url.replace('+', '%2B')}"

    def start(self) -> WebViewer:
        try:
            self.proxy = _ProxyServer(self.port, free_port(), content_policy(self.grpc_port))
        except OSError as exc:
            raise ViewerError(f"--rerun-web {self.port}: cannot listen on 127.0.0.1 ({exc.strerror})") from None
        files = self.proxy.upstream_port
        args = [rerun_executable(), "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port", str(files)]
        args += ["--port", str(self.grpc_port), "--server-memory-limit", self.memory_limit]
        self.process = subprocess.Popen(
            args, env=viewer_env(), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        try:
            wait_listening(self.process, self.grpc_port, "the web viewer's gRPC server")
            wait_listening(self.process, files, "the web viewer")
        except ViewerError:
            self.stop()
            raise
        self.serving = threading.Thread(target=self.proxy.serve_forever, name="objslam-web-viewer", daemon=True)
        self.serving.start()
        return self

    def stop(self) -> None:
        if self.proxy is not None:
            if self.serving is not None:
                self.proxy.shutdown()
            self.proxy.server_close()
            self.proxy, self.serving = None, None
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.process = None
