"""Where the viewer's data goes: an ``.rrd`` file, a web viewer served on 127.0.0.1, a native viewer.

The web viewer (``service.viewer_web``) and a spawned native viewer are the ``rerun`` executable that ships with
``rerun-sdk``, run as a child process bound to 127.0.0.1 (the SDK's own in-process web server listens on every
interface). Each child runs with Rerun's usage analytics and telemetry off (``viewer_env``).
"""

from __future__ import annotations

import importlib.util
import logging
import os
import socket
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import urlparse

import rerun as rr

from service.config import ViewerSettings
from service.viewer import blueprint

if TYPE_CHECKING:
    from service.viewer_web import WebViewer

log = logging.getLogger(__name__)

START_TIMEOUT_S = 15.0
LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")


class ViewerError(RuntimeError):
    """A viewer could not be started (a port in use, no ``rerun`` executable)."""


def viewer_env() -> dict[str, str]:
    """The environment of a viewer objslam starts: Rerun's analytics off (its pipeline is off whenever ``CI`` is
    set, re_analytics ``Pipeline::new``) and its OpenTelemetry stack off."""
    env = dict(os.environ)
    env.update(CI=env.get("CI") or "true", TELEMETRY_ENABLED="false")
    env.pop("FORCE_RERUN_ANALYTICS", None)
    env.pop("RERUN_TELEMETRY_ENDPOINT", None)
    return env


def rerun_executable() -> str:
    """The ``rerun`` executable that ships with the installed ``rerun-sdk`` (package ``rerun_cli``)."""
    spec = importlib.util.find_spec("rerun_cli")
    origin = spec.origin if spec is not None else None
    path = Path(origin or ".").with_name("rerun.exe" if sys.platform.startswith("win") else "rerun")
    if origin is None or not path.is_file():
        raise ViewerError(f"the rerun executable is missing: {path} (reinstall rerun-sdk)")
    return str(path)


def reachable(host: str, port: int, timeout: float = 0.3) -> bool:
    """Something accepts TCP connections on ``host:port``."""
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def free_port() -> int:
    """A TCP port of 127.0.0.1 that nothing listens on now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_listening(process: subprocess.Popen[bytes], port: int, what: str) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while not reachable("127.0.0.1", port):
        if process.poll() is not None or time.monotonic() > deadline:
            process.kill()
            raise ViewerError(f"{what} did not start on 127.0.0.1:{port} (exit code {process.poll()})")
        time.sleep(0.05)


def native_viewer(url: str) -> str | None:
    """The gRPC url of a native viewer: the one listening at ``url``, or one started there (on this machine, with
    a display). None, with a warning, when there is none and none can be started: the run goes on without it."""
    parsed = urlparse(url)
    host, port = parsed.hostname or "127.0.0.1", parsed.port or 9876
    if reachable(host, port):
        return url
    if host not in LOCAL_HOSTS or not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        log.warning("--rerun: no viewer listens at %s and none can be started here (no display); not streaming", url)
        return None
    args = [rerun_executable(), "--bind", "127.0.0.1", "--port", str(port), "--expect-data-soon"]
    process = subprocess.Popen(  # the viewer stays open after objslam ends: its own session
        args, env=viewer_env(), stdin=subprocess.DEVNULL, start_new_session=True
    )
    try:
        wait_listening(process, port, "the native viewer")
    except ViewerError as exc:
        log.warning("--rerun: %s; not streaming", exc)
        return None
    return f"rerun+http://127.0.0.1:{port}/proxy"


@dataclass
class Outlets:
    """A recording stream with its sinks, and the web viewer it may have started."""

    recording: rr.RecordingStream
    names: list[str]
    web: WebViewer | None = None

    def flush(self, timeout: float = 5.0) -> None:
        """Send what was logged (the ``.rrd`` gets its footer) and close the sinks."""
        try:
            self.recording.flush(timeout_sec=timeout)
        except Exception as exc:  # a viewer that went away must not fail the run
            log.warning("viewer: flushing failed: %s", " ".join(str(exc).split()))
        try:
            self.recording.disconnect()
        except Exception as exc:
            log.warning("viewer: closing failed: %s", " ".join(str(exc).split()))

    def stop_web(self) -> None:
        if self.web is not None:
            self.web.stop()


def open_outlets(settings: ViewerSettings, rrd: Path | None, robot: str) -> Outlets | None:
    """A recording stream to the ``.rrd`` file ``rrd`` and to the viewers ``settings`` ask for; None for none."""
    sinks: list[Any] = []
    names: list[str] = []
    web: WebViewer | None = None
    if rrd is not None:
        Path(rrd).parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rr.FileSink(str(rrd)))
        names.append(str(rrd))
    if settings.web_port is not None:
        from service.viewer_web import WebViewer

        web = WebViewer(settings.web_port, settings.memory_limit).start()
        sinks.append(rr.GrpcSink(web.grpc_url))
        names.append(web.url)
    url = native_viewer(settings.connect) if settings.native else None
    if url is not None:
        sinks.append(rr.GrpcSink(url))
        names.append(url)
    if not sinks:
        return None
    recording = rr.RecordingStream(f"objslam-{robot}", recording_id=uuid.uuid4(), send_properties=True)
    recording.set_sinks(*sinks, default_blueprint=blueprint())
    return Outlets(recording, names, web)
