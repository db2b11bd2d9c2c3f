"""A benchmark rig: a zenoh router in this process and ``objslam serve`` in a subprocess connected to it."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import zenoh


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def router(port: int) -> zenoh.Session:
    """A zenoh router listening on 127.0.0.1:``port`` (no multicast scouting)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def client(endpoint: str) -> zenoh.Session:
    """A client session connected to ``endpoint`` (e.g. a second querier beside the router's own session)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def query_status(session: zenoh.Session, key: str, timeout: float = 2.0) -> dict | None:
    """The JSON reply on ``key``, or None when nothing answered within ``timeout``."""
    for reply in session.get(key, timeout=timeout):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return None


def require_status(session: zenoh.Session, key: str, timeout: float = 2.0) -> dict:
    """The JSON reply on ``key``; RuntimeError when nothing answered within ``timeout``."""
    status = query_status(session, key, timeout)
    if status is None:
        raise RuntimeError(f"no reply on {key} within {timeout:g} s")
    return status


def start_serve(
    endpoint: str, robot: str, env: dict[str, str] | None = None, prefix: list[str] | None = None
) -> tuple[subprocess.Popen, Path]:
    """``objslam serve`` as a client of ``endpoint`` (``prefix``: a command it runs under, e.g. a profiler); its
    log goes to the returned file."""
    log = Path(tempfile.mkstemp(prefix=f"objslam-serve-{robot}-", suffix=".log")[1])
    command = [sys.executable, "-m", "service", "serve", "--mode", "client", "--connect", endpoint, "--robot", robot]
    with log.open("w") as out:
        proc = subprocess.Popen(
            [*(prefix or []), *command],
            env={**os.environ, **(env or {})},
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    return proc, log


def wait_for_status(
    session: zenoh.Session, key: str, proc: subprocess.Popen, log: Path, timeout: float = 120.0
) -> dict:
    """The first status reply of a starting service; RuntimeError (with its log's tail) if it dies or hangs."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"objslam serve exited with {proc.returncode}: {log.read_text()[-2000:]}")
        status = query_status(session, key, timeout=1.0)
        if status is not None:
            return status
        time.sleep(0.2)
    raise RuntimeError(f"objslam serve did not answer on {key} within {timeout:.0f} s")


def stop_serve(proc: subprocess.Popen, wrapped: bool = False) -> None:
    """SIGTERM to serve, then wait; SIGKILL after 30 s. ``wrapped``: ``proc`` is the command serve runs under
    (``start_serve``'s prefix): serve, its child, gets the signal, and the profiler writes its output as it exits."""
    children = Path(f"/proc/{proc.pid}/task/{proc.pid}/children")
    kids = children.read_text().split() if wrapped and children.exists() else []
    if kids:
        os.kill(int(kids[0]), 15)
    else:
        proc.terminate()
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
