"""Querying a running service over zenoh and printing the replies."""

from __future__ import annotations

import json
from typing import Any

from rich.console import Console
from rich.table import Table

from service.config import Settings
from service.zenoh_session import open_session


def query(settings: Settings, what: str, timeout: float | None = None) -> dict[str, Any]:
    """The JSON reply of ``<prefix>/<robot>/<what>``; TimeoutError when no service answers."""
    key = f"{settings.key_prefix}/{what}"
    session = open_session(settings.zenoh, "client")
    try:
        timeout = timeout or settings.zenoh.query_timeout_s
        for reply in session.get(key, timeout=timeout):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())
            error = reply.err.payload.to_string() if reply.err is not None else "(no payload)"
            raise RuntimeError(f"{key}: service replied with an error: {error}")
    finally:
        session.close()
    raise TimeoutError(f"no reply on {key} within {timeout:.1f} s (is `objslam serve` running and reachable?)")


def render_reply(console: Console, what: str, reply: dict[str, Any]) -> None:
    """A human-readable table of a reply."""
    if what == "status":
        table = Table(title=f"objslam status: {reply.get('robot')}", show_header=False)
        for key, value in reply.items():
            if key == "latency":
                continue
            table.add_row(key, json.dumps(value) if isinstance(value, (dict, list)) else str(value))
        console.print(table)
        lat = Table(title="stage latency (ms)")
        for col in ("stage", "n", "p50", "p95", "p99", "max"):
            lat.add_column(col)
        for stage, s in reply.get("latency", {}).items():
            if s.get("n"):
                lat.add_row(stage, str(s["n"]), *(str(s[k]) for k in ("p50_ms", "p95_ms", "p99_ms", "max_ms")))
        console.print(lat)
    elif what == "trajectory":
        poses = reply.get("poses", [])
        console.print(f"{len(poses)} poses ({reply.get('format')})")
        for row in poses[-10:]:
            console.print(" ".join(f"{v:.4f}" for v in row))
    else:
        items = reply.get(what, [])
        console.print(f"{len(items)} {what}")
        for item in items[:50]:
            console.print(json.dumps(item))
